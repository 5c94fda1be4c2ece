"""A region's outline in bed mm: the area it shows the operator when that is not its blocks.

A layer shift or a detached part is reported as the area where the layer is
and should not be, and where it should be and is not
(:func:`~layerwatch.analysis.part_registration.moved_area`), not as the HOG
blocks that happened to fire at its edges. :func:`outline_mm` turns such a
top-view mask into polygons in bed mm (:attr:`~layerwatch.analysis.result.Region.outline_mm`,
stored with the result); :func:`outline_mask` draws them back into a top view.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.geometry.topview import TopView

__all__ = ["Outline", "outline_mask", "outline_mm", "region_box"]

#: polygons, each ``((x, y), ...)`` in bed mm
Outline = tuple[tuple[tuple[float, float], ...], ...]


def outline_mm(mask: np.ndarray, topview: TopView, min_area_mm2: float = 1.0) -> Outline:
    """Outlines of the connected parts of a top-view mask and of their holes, in bed mm.

    Parameters
    ----------
    mask : ndarray, bool, shape topview.shape
    topview : TopView
    min_area_mm2 : float
        Parts smaller than this are left out (mm^2).

    Returns
    -------
    Outline
        One polygon per connected part (8-connected) and per hole in one,
        vertices in bed mm rounded to 0.01 mm; the area is inside an odd
        number of them (:func:`outline_mask`). The two bands of a shifted
        layer meet at its corners and enclose the part: that is a hole.
    """
    m = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    min_px = min_area_mm2 * topview.px_per_mm ** 2
    out = []
    for c in contours:
        if cv2.contourArea(c) < min_px:
            continue
        xy = np.round(topview.to_mm(c.reshape(-1, 2).astype(np.float64)), 2)
        out.append(tuple((float(x), float(y)) for x, y in xy))
    return tuple(out)


def outline_mask(outline: Outline, topview: TopView) -> np.ndarray:
    """The top-view pixels inside an odd number of the polygons of ``outline`` or on one, bool (H, W)."""
    out = np.zeros((int(topview.shape[0]), int(topview.shape[1])), np.uint8)
    polys = [np.round(topview.to_px(np.asarray(p, np.float64))).astype(np.int32) for p in outline if len(p)]
    if polys:
        cv2.fillPoly(out, polys, 1)  # one scan of all edges: a hole's polygon inside its part's cancels
        cv2.polylines(out, polys, True, 1)
    return out.astype(bool)


def region_box(bbox_mm: tuple[float, float, float, float], topview: TopView,
               shape: tuple[int, int]) -> tuple[slice, slice] | None:
    """A region's bed-mm box ``(xmin, ymin, xmax, ymax)`` as top-view rows and columns, clipped to ``shape``
    (both ends included, as the regions' boxes are drawn); None when nothing of it lies in the view."""
    (u0, v0), (u1, v1) = np.round(topview.to_px(np.array([bbox_mm[:2], bbox_mm[2:]], float))).astype(int)
    h, w = int(shape[0]), int(shape[1])
    us, vs = sorted((int(u0), int(u1))), sorted((int(v0), int(v1)))
    u_lo, u_hi, v_lo, v_hi = max(0, us[0]), min(w, us[1] + 1), max(0, vs[0]), min(h, vs[1] + 1)
    if u_hi <= u_lo or v_hi <= v_lo:
        return None
    return slice(v_lo, v_hi), slice(u_lo, u_hi)
