"""References shared between the pipelines of one process: a farm renders a layer of a file once.

A farm prints the same parts again and again, on many printers. Each printer's
:class:`~layerwatch.pipeline.step.LayerPipeline` renders its references incrementally
(:class:`~layerwatch.render.fast.StackRenderer`), and the reference of a layer (image, footprint,
HOG) is a function of the G-code, the top view, the render settings, the posed camera (the camera
view's rays and parallax), the camera matching and the analysis settings (its HOG) alone. Printers
whose jobs agree on all of these get the same reference, array for array: :class:`SharedReferences`
keeps the references that the pipelines of a process rendered, keyed by :func:`reference_identity`
and the layer, so the second printer of a file reads the first one's.

What is shared is read-only: the arrays of a stored reference are made non-writeable, so a
pipeline that wrote into one would raise rather than change another printer's reference.

When is a reference shared? Only when every input is equal, the camera model included (its
intrinsics, distortion, image size and bed pose, exactly): printers calibrated one by one have
poses that differ in the last digits and share nothing; printers of a farm that reuse one
calibration for identical mounts and print the same file share every layer. A printer whose
reference was read from the store does not render it; its renderer catches up (the layers
between in one pass) when it next renders one itself, with the same result.

Memory is bounded: the least recently used references are dropped past ``max_mb``
(about 1.1 MB a reference at 600 x 600 px).
"""

from __future__ import annotations

import hashlib
import json
import threading
from collections import OrderedDict
from typing import Protocol

import numpy as np

from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.config import JobConfig
from layerwatch.render.cache import RENDER_VERSION, toolpath_hash

__all__ = ["SharedReferences", "reference_identity"]


class Reference(Protocol):
    """What is stored: a :class:`layerwatch.pipeline.step.Reference` (its arrays)."""

    image: np.ndarray
    footprint: np.ndarray
    hog: tuple[np.ndarray, np.ndarray] | None
    registration: np.ndarray | None


def reference_identity(toolpath: Toolpath, camera: CameraModel, config: JobConfig, topview: TopView,
                       match_camera: bool) -> str:
    """Hex key of everything a pipeline's references depend on, but the layer.

    The toolpath's geometry (:func:`~layerwatch.render.cache.toolpath_hash`), the render settings,
    the top view, the camera's intrinsics, distortion, image size and pose (exact values), whether
    references are camera-matched, the analysis settings (the reference's HOG) and the renderer's
    version. Pipelines with the same identity render the same reference of every layer.
    """
    cam = camera
    blob = json.dumps(
        {
            "v": RENDER_VERSION,
            "gcode": toolpath_hash(toolpath),
            "render": config.render.model_dump(mode="json"),
            "topview": topview.to_dict(),
            "analysis": config.analysis.model_dump(mode="json"),
            "match_camera": bool(match_camera),
            "camera": {name: None if value is None else np.asarray(value, np.float64).tobytes().hex()
                       for name, value in (("K", cam.K), ("dist", cam.dist), ("size", cam.image_size),
                                           ("rvec", cam.rvec), ("tvec", cam.tvec))},
        },
        sort_keys=True,
    )
    return hashlib.sha256(blob.encode()).hexdigest()


def _reference_bytes(ref: Reference) -> int:
    hog = ref.hog or ()
    reg = 0 if ref.registration is None else ref.registration.nbytes
    return int(ref.image.nbytes + ref.footprint.nbytes + reg + sum(a.nbytes for a in hog))


def _freeze(ref: Reference) -> None:
    for a in (ref.image, ref.footprint, *(() if ref.registration is None else (ref.registration,)), *(ref.hog or ())):
        a.flags.writeable = False


class SharedReferences:
    """The references of a process's pipelines, by (identity, layer); least recently used dropped past ``max_mb``.

    Thread-safe. Two pipelines that miss the same layer at once both render it (the same
    reference); the one stored last stays.

    Parameters
    ----------
    max_mb : float
        Memory the stored references may hold, MB (their arrays' bytes).

    Attributes
    ----------
    hits, misses : int
        Look-ups answered from the store, and not.
    """

    def __init__(self, max_mb: float = 256.0) -> None:
        if not max_mb > 0:
            raise ValueError(f"max_mb must be > 0, got {max_mb}")
        self.max_bytes = int(max_mb * 2**20)
        self._refs: OrderedDict[tuple[str, int], Reference] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    @property
    def nbytes(self) -> int:
        """Bytes held by the stored references' arrays."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._refs)

    def get(self, identity: str, layer: int) -> Reference | None:
        """The stored reference of ``layer`` for pipelines of ``identity``, or None (counted as a miss)."""
        with self._lock:
            ref = self._refs.get((identity, int(layer)))
            if ref is None:
                self.misses += 1
                return None
            self._refs.move_to_end((identity, int(layer)))
            self.hits += 1
            return ref

    def put(self, identity: str, layer: int, ref: Reference) -> None:
        """Store ``ref`` (its arrays made read-only); a reference larger than the whole budget is not stored."""
        size = _reference_bytes(ref)
        if size > self.max_bytes:
            return
        _freeze(ref)
        key = (identity, int(layer))
        with self._lock:
            old = self._refs.pop(key, None)
            if old is not None:
                self._bytes -= _reference_bytes(old)
            self._refs[key] = ref
            self._bytes += size
            while self._bytes > self.max_bytes:
                _, dropped = self._refs.popitem(last=False)
                self._bytes -= _reference_bytes(dropped)

    def clear(self) -> None:
        """Drop every stored reference."""
        with self._lock:
            self._refs.clear()
            self._bytes = 0
