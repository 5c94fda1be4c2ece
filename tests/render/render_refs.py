"""Independent NumPy references for the render tests."""

from __future__ import annotations

import numpy as np


def brute_capsules(toolpath, index, topview, *, height=False):
    """Independent reference: per-pixel distance to every segment with NumPy.

    Returns the footprint of layer ``index`` (bool (H, W)) or, with
    ``height=True``, the max-profile height map of layers 0..index.
    """
    H, W = topview.shape
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    xy = topview.to_mm(np.stack([uu, vv], -1))
    sl = toolpath.up_to(index) if height else toolpath.layer_slice(index)
    out = np.zeros((H, W), np.float64 if height else bool)
    hs = np.repeat([la.height for la in toolpath.layers], [la.n_segments for la in toolpath.layers])
    for a, b, w, z, h in zip(
        toolpath.start[sl], toolpath.end[sl], toolpath.width[sl], toolpath.z[sl], hs[sl], strict=True
    ):
        d = b - a
        L2 = float(d @ d)
        t = np.clip(((xy - a) @ d) / L2, 0, 1) if L2 > 0 else np.zeros((H, W))
        q = xy - a - t[..., None] * d
        dist = np.hypot(q[..., 0], q[..., 1]) / (w / 2)
        inside = dist < 1
        if height:
            prof = np.where(inside, z - h / 2 + h / 2 * np.sqrt(np.clip(1 - dist**2, 0, 1)), 0)
            out = np.maximum(out, prof)
        else:
            out |= inside
    return out
