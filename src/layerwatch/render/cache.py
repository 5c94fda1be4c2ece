"""Render once, reuse: an on-disk cache of references and masks.

Entries are keyed by the G-code (hash of the toolpath's segment arrays, or
of the file bytes when given), the render settings, the top view, the
backend and the layer index, so a series of identical parts renders each
layer once (the paper's mass-production case). Entries are written to a
temporary file in the cache folder and renamed into place, so a crash or a
failed render never leaves a partial entry.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from layerwatch.errors import RenderError
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.topview import TopView
from layerwatch.render.fast import Rendered
from layerwatch.render.settings import RenderSettings

__all__ = ["ReferenceCache", "toolpath_hash", "file_hash"]

#: bump when the renderer's output changes for the same inputs
RENDER_VERSION = 1


def toolpath_hash(toolpath: Toolpath) -> str:
    """SHA-256 (hex) of the toolpath geometry: endpoints, z, width and layer slices."""
    h = hashlib.sha256()
    for a in (toolpath.start, toolpath.end, toolpath.z, toolpath.width):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(np.array([(la.seg_start, la.seg_stop) for la in toolpath.layers], np.int64).tobytes())
    h.update(np.array([(la.z, la.height) for la in toolpath.layers], np.float64).tobytes())
    return h.hexdigest()


def file_hash(path: str | Path, chunk: int = 1 << 20) -> str:
    """SHA-256 (hex) of a file, read in chunks (memory bounded)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


class ReferenceCache:
    """Folder of rendered layers (``.npz``: image, height, mask, light; the registrations' image when rendered).

    Parameters
    ----------
    directory : str or Path
        Created when missing.
    """

    def __init__(self, directory: str | Path):
        self.directory = Path(directory)
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RenderError(f"cannot create cache folder {self.directory} ({exc}); pick a writable --cache.") from None
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(gcode_hash: str, settings: RenderSettings, topview: TopView, layer: int, kind: str = "ref") -> str:
        """Hex key of one entry (G-code hash + settings + top view + layer + kind)."""
        blob = json.dumps(
            {
                "v": RENDER_VERSION,
                "gcode": gcode_hash,
                "settings": settings.model_dump(mode="json"),
                "topview": topview.to_dict(),
                "layer": int(layer),
                "kind": kind,
            },
            sort_keys=True,
        )
        return hashlib.sha256(blob.encode()).hexdigest()[:40]

    def path(self, key: str) -> Path:
        return self.directory / key[:2] / f"{key}.npz"

    def get(self, key: str) -> Rendered | None:
        """The cached entry, or ``None`` (also for an unreadable entry, which is removed)."""
        p = self.path(key)
        if not p.is_file():
            return None
        try:
            with np.load(p) as z:
                meta = z["meta"]
                return Rendered(
                    image=z["image"], height=z["height"], mask=z["mask"], layer=int(meta[0]),
                    z=float(meta[1]), light=z["light"], clipped=int(meta[2]),
                    registration=z["registration"] if "registration" in z.files else None,
                )
        except Exception:  # corrupt entry: forget it, render again
            p.unlink(missing_ok=True)
            return None

    def put(self, key: str, rendered: Rendered) -> Path:
        """Store an entry atomically (temporary file + rename)."""
        p = self.path(key)
        p.parent.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        # (typed Any: NumPy's stubs read any ``**kwds`` as its ``allow_pickle`` flag, which NumPy < 2.1, still
        # supported, does not have: it would store the flag as one more array)
        arrays: dict[str, Any] = {"image": rendered.image, "height": rendered.height, "mask": rendered.mask,
                            "light": rendered.light.astype(np.float16),
                            "meta": np.array([rendered.layer, rendered.z, rendered.clipped], np.float64)}
        if rendered.registration is not None:
            arrays["registration"] = rendered.registration
        np.savez_compressed(buf, **arrays)
        fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=".tmp-", suffix=".npz")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(buf.getvalue())
            os.replace(tmp, p)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return p

    def get_or_render(self, key: str, render: Callable[[], Rendered]) -> Rendered:
        """Return the cached entry or call ``render()`` and store its result.

        A ``render`` that raises stores nothing.
        """
        hit = self.get(key)
        if hit is not None:
            self.hits += 1
            return hit
        self.misses += 1
        out = render()
        self.put(key, out)
        return out
