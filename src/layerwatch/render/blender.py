"""Optional photoreal backend: Blender Cycles through the ``blender`` executable.

The layer's beads are exported as one mesh of rounded prisms (raw binary arrays), a
JSON job describes the scene (material, ring light, bed, markers, top-down
orthographic camera matching the :class:`TopView`), and
``blender -b -P blender_scene.py -- job.json`` renders one PNG in a
subprocess. Height map and footprint come from the fast renderer (Blender
gives only the picture).

Only the layers within ``layers_visible_below`` of the rendered layer are
exported (deeper layers are hidden or fully darkened anyway).

References
----------
Petsiuk & Pearce (2022), Section 2.4 (Blender Cycles references, Principled
+ Translucent BSDF with noise, ring light).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import cv2
import numpy as np

from layerwatch.errors import LayerwatchError, RenderError
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.topview import TopView
from layerwatch.render.fast import Rendered, StackRenderer, _check_index
from layerwatch.render.settings import RenderSettings

__all__ = ["MissingBlenderError", "find_blender", "bead_mesh", "render_layer_blender"]

SCENE_SCRIPT = Path(__file__).with_name("blender_scene.py")


class MissingBlenderError(LayerwatchError):
    """The ``blender`` executable is not installed."""


def find_blender(executable: str | None = None) -> str:
    """Path of the Blender executable (``$LAYERWATCH_BLENDER`` or ``blender`` on PATH).

    Raises
    ------
    MissingBlenderError
        One line naming how to install it.
    """
    name = executable or os.environ.get("LAYERWATCH_BLENDER", "blender")
    path = shutil.which(name)
    if path is None:
        raise MissingBlenderError(
            "the Blender backend needs the `blender` executable: run `apt-get install blender` "
            "(or set LAYERWATCH_BLENDER), or use --backend fast."
        )
    return path


def bead_mesh(start, end, ztop, width, height, profile: int = 5):
    """Rounded prisms along segments, as a flat polygon mesh.

    Parameters
    ----------
    start, end : ndarray, shape (S, 2)
        Segment endpoints, mm (each is extended by half a width: approximate
        round ends).
    ztop, width, height : ndarray, shape (S,)
        Top of the bead, bead width and height, mm.
    profile : int
        Points on the rounded top of the cross-section.

    Returns
    -------
    verts : ndarray, shape (V, 3), float32
    loops : ndarray, shape (L,), int32
        Vertex indices of all faces, concatenated.
    sizes : ndarray, shape (F,), int32
        Vertices per face.
    """
    start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
    n = start.shape[0]
    if n == 0:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.int32), np.zeros(0, np.int32)
    d = end - start
    length = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(length > 1e-9, d / np.maximum(length, 1e-9), np.array([1.0, 0.0]))
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
    hw = 0.5 * np.asarray(width, np.float64)[:, None]
    p0, p1 = start - d * hw, end + d * hw
    th = np.linspace(0.0, np.pi, profile)
    # cross-section: bottom-right, arc right->left, bottom-left  (K points)
    off = np.concatenate([[1.0], np.cos(th), [-1.0]])  # along the normal, x half-width
    h = np.asarray(height, np.float64)[:, None]
    zt = np.asarray(ztop, np.float64)[:, None]
    zk = np.concatenate([np.full((n, 1), -1.0), np.sin(th)[None].repeat(n, 0), np.full((n, 1), -1.0)], 1)
    z = zt - 0.5 * h + 0.5 * h * zk  # bottom = zt - h
    k = off.size
    verts = np.empty((n, 2, k, 3))
    for e, p in enumerate((p0, p1)):
        verts[:, e, :, :2] = p[:, None, :] + off[None, :, None] * hw[:, :, None] * nrm[:, None, :]
        verts[:, e, :, 2] = z
    base = (np.arange(n) * 2 * k)[:, None]
    j = np.arange(k)
    jn = (j + 1) % k
    quads = np.stack([j, jn, k + jn, k + j], axis=1)[None] + base[:, :, None]  # (n, k, 4)
    cap0 = j[::-1][None] + base
    cap1 = (k + j)[None] + base
    loops = np.concatenate([quads.reshape(n, -1), cap0, cap1], axis=1).ravel()
    sizes = np.tile(np.concatenate([np.full(k, 4), [k, k]]), n)
    return verts.reshape(-1, 3).astype(np.float32), loops.astype(np.int32), sizes.astype(np.int32)


def render_layer_blender(
    toolpath: Toolpath,
    index: int,
    topview: TopView,
    settings: RenderSettings | None = None,
    *,
    executable: str | None = None,
    threads: int = 2,
    ring_strength: float = 6.0,
) -> Rendered:
    """Render layer ``index`` with Blender Cycles (subprocess).

    Returns
    -------
    Rendered
        ``image`` from Cycles (grey uint8 (H, W)); ``height``, ``mask`` and
        ``light`` from the fast renderer.

    Raises
    ------
    MissingBlenderError
        ``blender`` is not installed.
    RenderError
        Blender failed, crashed or ran past ``settings.blender_timeout_s``.
    """
    s = settings or RenderSettings()
    exe = find_blender(executable)
    index = _check_index(toolpath, index)
    fast = StackRenderer(toolpath, topview, s).render(index)
    lo = max(0, index - s.layers_visible_below)
    a, b = toolpath.layers[lo].seg_start, toolpath.layers[index].seg_stop
    lh = np.concatenate(
        [np.full(la.n_segments, la.height if la.height > 0 else 0.2) for la in toolpath.layers[lo : index + 1]]
    )
    verts, loops, sizes = bead_mesh(
        toolpath.start[a:b], toolpath.end[a:b], toolpath.z[a:b], toolpath.width[a:b], lh
    )
    H, W = topview.shape
    with tempfile.TemporaryDirectory(prefix="layerwatch-blender-") as tmp:
        t = Path(tmp)
        for name, arr in (("verts", verts), ("loops", loops), ("sizes", sizes)):
            (t / f"{name}.bin").write_bytes(np.ascontiguousarray(arr).astype(arr.dtype.newbyteorder("<")).tobytes())
        job = {
            "verts": str(t / "verts.bin"),
            "loops": str(t / "loops.bin"),
            "sizes": str(t / "sizes.bin"),
            "output": str(t / "out.png"),
            "resolution": [W, H],
            "center_mm": list(topview.center_mm),
            "size_mm": [topview.width_mm, topview.height_mm],
            "z_top": float(toolpath.layers[index].z),
            "material_rgb": list(s.material_rgb),
            "bed_rgb": list(s.bed_rgb),
            "markers_mm": [list(m) for m in (s.markers_mm or [])],
            "marker_diameter_mm": s.marker_diameter_mm,
            "light_elevation_deg": s.light_elevation_deg,
            "ring_strength": ring_strength,
            "samples": s.blender_samples,
            "threads": threads,
        }
        (t / "job.json").write_text(json.dumps(job))
        cmd = [exe, "-b", "--factory-startup", "-noaudio", "--python-exit-code", "3", "-P", str(SCENE_SCRIPT), "--", str(t / "job.json")]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=s.blender_timeout_s)
        except subprocess.TimeoutExpired:
            raise RenderError(
                f"Blender did not finish layer {index} within {s.blender_timeout_s:.0f} s; "
                "raise render.blender_timeout_s or lower render.blender_samples."
            ) from None
        except OSError as exc:
            raise RenderError(f"cannot start Blender ({exc}); check `{exe}` runs.") from None
        out = t / "out.png"
        img = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE) if out.is_file() else None
        if proc.returncode != 0 or img is None or img.shape != (H, W):
            tail = " | ".join((proc.stderr or proc.stdout or "").strip().splitlines()[-3:])
            raise RenderError(
                f"Blender failed on layer {index} (exit {proc.returncode}): {tail[:300]}; "
                "run with --backend fast or check the Blender installation."
            )
    return Rendered(img, fast.height, fast.mask, index, fast.z, fast.light, fast.clipped)
