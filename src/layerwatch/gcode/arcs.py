"""G2/G3 arc geometry for the kernel: centre (I/J or R form), sweep, chord count."""

from __future__ import annotations

import math

import numba as nb

__all__ = ["arc_geometry"]


@nb.njit(cache=True)
def arc_geometry(x0, y0, x1, y1, ccw, has_ij, has_r, i_off, j_off, r, chord_tol):
    """Centre, radii, start angle, sweep and chord count of an XY arc.

    Parameters
    ----------
    x0, y0, x1, y1 : float
        Start and end point, mm.
    ccw : bool
        True for G3 (counter-clockwise), False for G2.
    has_ij, has_r : bool
        Which centre form the line used.
    i_off, j_off : float
        Centre offset from the start (I/J form), mm.
    r : float
        Radius (R form), mm; negative selects the arc longer than 180 degrees.
    chord_tol : float
        Maximum sagitta of each chord, mm.

    Returns
    -------
    ok : bool
        False when the arc has no usable centre (no I/J, and R with start == end).
    cx, cy, r0, r1, a0, sweep : float
        Centre, start/end radius (mm), start angle and signed sweep (rad;
        a full circle when start == end in I/J form).
    k : int
        Number of chords, so that each chord's sagitta <= ``chord_tol`` (the kernel
        bounds it further by the arc's length, see ``kernel._arc_chords``).
    """
    dxy = math.hypot(x1 - x0, y1 - y0)
    if has_ij:
        cx = x0 + i_off
        cy = y0 + j_off
    elif has_r and dxy > 1e-12:
        h2 = r * r - dxy * dxy / 4.0
        h = math.sqrt(h2) if h2 > 0 else 0.0
        sgn = 1.0 if ccw == (r > 0) else -1.0  # side of the chord the centre lies on
        cx = (x0 + x1) / 2.0 - sgn * h * (y1 - y0) / dxy
        cy = (y0 + y1) / 2.0 + sgn * h * (x1 - x0) / dxy
    else:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1
    r0 = math.hypot(x0 - cx, y0 - cy)
    r1 = math.hypot(x1 - cx, y1 - cy)
    a0 = math.atan2(y0 - cy, x0 - cx)
    sweep = math.atan2(y1 - cy, x1 - cx) - a0
    if ccw:
        if sweep <= 1e-12:
            sweep += 2.0 * math.pi
    elif sweep >= -1e-12:
        sweep -= 2.0 * math.pi
    if not (math.isfinite(r0) and math.isfinite(r1) and math.isfinite(sweep)):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1
    k = 1
    if r0 > 1e-9 and chord_tol < r0:
        step = 2.0 * math.acos(1.0 - chord_tol / r0)  # 0 when r0 >> chord_tol (|I| ~ 1e15)
        k = int(math.ceil(min(abs(sweep) / step, 1e6))) if step > 1e-12 else 1000000
    return True, cx, cy, r0, r1, a0, sweep, max(1, min(k, 1000000))
