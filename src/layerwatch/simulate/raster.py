"""Rasterisers of the simulator's own height field (independent of ``render.fast``).

Every deposited bead, strand or object is a *capsule* (a segment swept by a
disc of radius ``r``) with a rounded cross-section: at distance ``d`` from the
segment axis its top is ``b + c + a * sqrt(1 - (d / r_t)^2)``, an ellipse of
half-width ``r_t`` and half-height ``a`` sitting on the base ``b``. ``r_t``
varies along the segment (``r * (1 + amp * sin(phase + 2 pi s / 3 mm))``) to
imitate extrusion-rate noise. The height field keeps the maximum of all
stamps (a z-buffer seen from above) and a material id per cell.

Grids are addressed like a :class:`~layerwatch.geometry.topview.TopView`:
``u = ux0 + s * x``, ``v = vy0 - s * y`` with pixel centres at integers.
"""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit

__all__ = ["grid_params", "stamp_capsules", "capsule_mask"]

WOBBLE_MM = 3.0


def grid_params(topview) -> tuple[float, float, float]:
    """``(s, ux0, vy0)`` with ``u = ux0 + s x`` and ``v = vy0 - s y`` for a TopView."""
    h, w = topview.shape
    s = float(topview.px_per_mm)
    cx, cy = topview.center_mm
    return s, (w - 1) / 2.0 - s * cx, (h - 1) / 2.0 + s * cy


@njit(cache=True, inline="always")
def _row_span(x0, y0, dx, dy, y, r, ux0, s, umin, umax):
    """Columns ``[a, b]`` a capsule of radius ``r`` can cover on the row at height ``y``."""
    if abs(dy) < 1e-12:
        return umin, umax
    ta, tb = (y - r - y0) / dy, (y + r - y0) / dy
    if ta > tb:
        ta, tb = tb, ta
    ta, tb = max(ta, 0.0), min(tb, 1.0)
    if ta > tb:
        return 1, 0
    xa, xb = x0 + ta * dx, x0 + tb * dx
    if xa > xb:
        xa, xb = xb, xa
    a = max(int(np.floor(ux0 + s * (xa - r))), umin)
    b = min(int(np.ceil(ux0 + s * (xb + r))), umax)
    return a, b


@njit(cache=True)
def stamp_capsules(h, mat, base, seg, mat_id, s, ux0, vy0):
    """Stamp capsules into a height field, keeping the per-cell maximum.

    Parameters
    ----------
    h : float32 (H, W)
        Height field, mm (modified in place).
    mat : uint8 (H, W)
        Material id per cell (modified in place where a stamp wins).
    base : float32 (H, W)
        Per-cell base height used where a segment's ``b`` is NaN (draped
        strands); may be ``h`` itself copied beforehand.
    seg : float64 (N, 10)
        Rows ``x0, y0, x1, y1, r, b, c, a, amp, phase`` (mm, mm, -, rad).
    mat_id : uint8 (N,)
        Material of each segment.
    s, ux0, vy0 : float
        Grid mapping (see :func:`grid_params`).
    """
    H, W = h.shape
    two_pi = 2.0 * np.pi
    for k in range(seg.shape[0]):
        x0, y0, x1, y1 = seg[k, 0], seg[k, 1], seg[k, 2], seg[k, 3]
        r, b, c, a, amp, ph = seg[k, 4], seg[k, 5], seg[k, 6], seg[k, 7], seg[k, 8], seg[k, 9]
        rmax = r * (1.0 + abs(amp))
        if rmax <= 0.0:
            continue
        umin = int(np.floor(ux0 + s * (min(x0, x1) - rmax)))
        umax = int(np.ceil(ux0 + s * (max(x0, x1) + rmax)))
        vmin = int(np.floor(vy0 - s * (max(y0, y1) + rmax)))
        vmax = int(np.ceil(vy0 - s * (min(y0, y1) - rmax)))
        umin = max(umin, 0)
        vmin = max(vmin, 0)
        umax = min(umax, W - 1)
        vmax = min(vmax, H - 1)
        dx, dy = x1 - x0, y1 - y0
        L2 = dx * dx + dy * dy
        L = np.sqrt(L2)
        for v in range(vmin, vmax + 1):
            y = (vy0 - v) / s
            ua, ub = _row_span(x0, y0, dx, dy, y, rmax, ux0, s, umin, umax)
            for u in range(ua, ub + 1):
                x = (u - ux0) / s
                t = 0.0
                if L2 > 0.0:
                    t = ((x - x0) * dx + (y - y0) * dy) / L2
                    t = min(max(t, 0.0), 1.0)
                px, py = x0 + t * dx - x, y0 + t * dy - y
                d2 = px * px + py * py
                rt = r * (1.0 + amp * np.sin(ph + two_pi * t * L / 3.0))
                if d2 >= rt * rt:
                    continue
                q = 1.0 - d2 / (rt * rt)
                bb = b
                if np.isnan(bb):
                    bb = base[v, u]
                val = bb + c + a * np.sqrt(q)
                if val > h[v, u]:
                    h[v, u] = val
                    mat[v, u] = mat_id[k]


@njit(cache=True)
def _capsule_mask(out, p0, p1, r, s, ux0, vy0):
    H, W = out.shape
    for k in range(p0.shape[0]):
        x0, y0, x1, y1, rr = p0[k, 0], p0[k, 1], p1[k, 0], p1[k, 1], r[k]
        umin = max(int(np.floor(ux0 + s * (min(x0, x1) - rr))), 0)
        umax = min(int(np.ceil(ux0 + s * (max(x0, x1) + rr))), W - 1)
        vmin = max(int(np.floor(vy0 - s * (max(y0, y1) + rr))), 0)
        vmax = min(int(np.ceil(vy0 - s * (min(y0, y1) - rr))), H - 1)
        dx, dy = x1 - x0, y1 - y0
        L2 = dx * dx + dy * dy
        for v in range(vmin, vmax + 1):
            y = (vy0 - v) / s
            ua, ub = _row_span(x0, y0, dx, dy, y, rr, ux0, s, umin, umax)
            for u in range(ua, ub + 1):
                x = (u - ux0) / s
                t = 0.0
                if L2 > 0.0:
                    t = min(max(((x - x0) * dx + (y - y0) * dy) / L2, 0.0), 1.0)
                px, py = x0 + t * dx - x, y0 + t * dy - y
                if px * px + py * py <= rr * rr:
                    out[v, u] = True


def capsule_mask(start: np.ndarray, end: np.ndarray, half_width, topview) -> np.ndarray:
    """Footprint of capsules in a top view.

    Parameters
    ----------
    start, end : ndarray, shape (N, 2)
        Segment endpoints, bed mm.
    half_width : float or ndarray, shape (N,)
        Capsule radius (bead width / 2), mm.
    topview : TopView

    Returns
    -------
    ndarray, bool, shape topview.shape
        True where a pixel centre lies within ``half_width`` of a segment.
    """
    out = np.zeros(topview.shape, dtype=bool)
    p0 = np.ascontiguousarray(start, dtype=np.float64).reshape(-1, 2)
    p1 = np.ascontiguousarray(end, dtype=np.float64).reshape(-1, 2)
    r = np.broadcast_to(np.asarray(half_width, dtype=np.float64), (p0.shape[0],)).copy()
    if p0.shape[0]:
        s, ux0, vy0 = grid_params(topview)
        _capsule_mask(out, p0, p1, r, s, ux0, vy0)
    return out


def solid_area(start: np.ndarray, end: np.ndarray, half_width, topview, close_mm: float = 3.0):
    """Area covered by a layer: its capsule footprint closed over gaps up to ``close_mm``.

    Sparse infill leaves gaps between beads; the *area* of the layer (what a
    shifted or displaced layer uncovers) closes them with a disc of diameter
    ``close_mm``.

    Returns
    -------
    ndarray, bool, shape topview.shape
    """
    fp = capsule_mask(start, end, half_width, topview).astype(np.uint8)
    k = max(int(round(close_mm * topview.px_per_mm)) | 1, 3)
    pad = k
    padded = cv2.copyMakeBorder(fp, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    closed = cv2.morphologyEx(padded, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    return closed[pad:-pad, pad:-pad].astype(bool)
