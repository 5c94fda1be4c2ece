"""Small synthetic toolpaths for tests and demos (no slicer needed)."""

from __future__ import annotations

import numpy as np

from layerwatch.gcode.toolpath import FEATURES, Toolpath

__all__ = ["box_part"]


def _loop(x0, y0, x1, y1):
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    return c, np.roll(c, -1, axis=0)


def box_part(
    size_mm: float = 30.0,
    height_mm: float = 6.0,
    layer_h: float = 0.3,
    center: tuple[float, float] = (0.0, 0.0),
    width: float = 0.45,
    fin: bool = True,
) -> Toolpath:
    """A square block with two perimeters and alternating +-45 deg infill, plus a thin fin.

    Parameters
    ----------
    size_mm : float
        Side of the block, mm.
    height_mm, layer_h : float
        Print height and layer height, mm.
    center : (float, float)
        Block centre on the bed, mm.
    width : float
        Bead width, mm.
    fin : bool
        Add a 2-perimeter-thick (~0.9 mm) wall 12 mm long beside the block.

    Returns
    -------
    Toolpath
        Features: external_perimeter, perimeter, infill.
    """
    cx, cy = center
    h = size_mm / 2
    starts, ends, zs, feats = [], [], [], []
    ext, per, inf = (FEATURES.index(n) for n in ("external_perimeter", "perimeter", "infill"))
    n_layers = int(round(height_mm / layer_h))
    for k in range(n_layers):
        z = round((k + 1) * layer_h, 6)
        for off, code in ((0.0, ext), (width, per)):
            a, b = _loop(cx - h + off, cy - h + off, cx + h - off, cy + h - off)
            starts.append(a)
            ends.append(b)
            feats += [code] * 4
        # infill: lines at +-45 deg clipped to the inner square
        inner = h - 2 * width
        sp = 2 * width
        sgn = 1 if k % 2 == 0 else -1
        for c in np.arange(-2 * inner + sp / 2, 2 * inner, sp):
            # line x - sgn*y = c, within |x|,|y| <= inner
            ys = np.array([-inner, inner])
            xs = c + sgn * ys
            xs = np.clip(xs, -inner, inner)
            ys = (xs - c) * sgn
            if np.hypot(*(np.diff(xs), np.diff(ys))) < width:
                continue
            starts.append([[cx + xs[0], cy + ys[0]]])
            ends.append([[cx + xs[1], cy + ys[1]]])
            feats.append(inf)
        if fin:
            x0 = cx + h + 6.0
            a, b = _loop(x0, cy - 6.0, x0 + width, cy + 6.0)
            starts.append(a)
            ends.append(b)
            feats += [ext] * 4
        zs += [z] * (sum(len(s) for s in starts) - len(zs))
    return Toolpath.from_segments(
        np.concatenate(starts), np.concatenate(ends), np.array(zs), width=width,
        feature=np.array(feats, np.uint8), layer_height=layer_h, source="<box_part>",
    )
