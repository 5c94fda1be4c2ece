"""A true 3-D reference: the printed layers as an occupancy volume, ray-marched from the camera.

A height map (:mod:`layerwatch.render.camera_view`) keeps one surface per
top-view pixel, so everything under the highest bead of a column is solid
down to the bed. Windows through a wall, a cross-hole in an upright, the
space under an overhang or a bridge cannot be held: a ray that really passes
through them stops at a wall that is not there, and those edges light up
on clean layers.

:class:`OccupancyStack` keeps, for every *z slot* (the distinct layer tops of
the toolpath), the footprint of the beads printed in it as a bit-packed
raster on the box the print covers: ``(n_slots, h, b)`` uint8, at most 45 kB per
slot at 600 x 600 px (500 layers: 22.5 MB) when the part fills the view, a
fraction of it otherwise (a 40 mm part on a 150 mm square: ~1/14). A layer fills the slots its thickness spans, so
sequential prints and variable layer heights stack correctly. Short vertical
gaps (at most ``fill_layers`` slots, e.g. the one-layer slit under a sparse
infill line that crosses the previous layer's lines) are closed, as the
printed bead sags into them and no camera sees through them.

:func:`view_through_volume` follows every top-view pixel's camera ray as
:func:`~layerwatch.render.camera_view.view_from_camera` does, with the height
map as an upper envelope (empty space is skipped with it), but a point under
the envelope is solid only when its slot's bit is set there. Where a ray
meets material:

* the column's top surface (the ray came from above the height map): the
  shaded top view, as today;
* a side (the point just above on the ray is solid in the same column): a
  wall with layer lines, as today, facing from the slot's occupancy gradient;
* a *hidden* top surface (seen through a window or under a bridge: the sill,
  the floor of a hollow part): a flat bead lit as lower layers are, darkened
  with its depth below the layer plane (``depth_darkening``);
* the bed under an overhang or a bridge: the bed's albedo (flat, lit).

On a part without windows or overhangs every column is solid from the bed to
its top, and the result is the height-map reference pixel for pixel.

References
----------
Petsiuk & Pearce (2022), Section 2.3, eqs. (1)-(3) (the plane homography
whose rays are followed) and Section 2.4 (reference images from G-code).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit

from layerwatch.geometry.topview import TopView
from layerwatch.render.camera_view import (
    DEFAULT_LOOK,
    SKIP_PX,
    WallLook,
    bilinear,
    grown_box,
    ray_setup,
    skip_map,
    wall_light,
)

__all__ = ["OccupancyStack", "view_through_volume"]

_Z_TOL = 1e-4  # mm: a point this far above a slot's (rounded) top still belongs to it


#: rows (and bytes of 8 columns, times 8 px) added around the printed box when it grows, so that a part that
#: widens layer by layer does not copy its bits on every layer
_BOX_MARGIN_PX = 16


class OccupancyStack:
    """Bit-packed occupancy of the printed layers, one raster per z slot, on the box the print covers.

    Parameters
    ----------
    shape : (int, int)
        ``(H, W)`` of the top view.
    layer_z : array_like, shape (L,)
        Top of every layer of the toolpath, mm (print order).
    layer_height : array_like, shape (L,)
        Thickness of every layer, mm (non-positive or non-finite: 0.2 mm).
    fill_layers : int
        Vertical gaps of at most this many slots between two printed slots of
        a pixel are closed (see module notes); 0 keeps every gap.

    Attributes
    ----------
    tops : ndarray, shape (S,), float64
        Ascending slot tops, mm; slot ``s`` spans ``(tops[s - 1], tops[s]]`` (``tops[-1]`` = 0).
    bits : ndarray, shape (S_alloc, h, b), uint8
        Occupancy bits (little bit order along rows) of the box :attr:`origin` ``(r0, b0)``: rows
        ``r0 .. r0 + h`` and columns ``8 b0 .. 8 (b0 + b)`` of the top view (byte ``j`` of a row is byte
        ``b0 + j`` of the whole row's :func:`numpy.packbits`), allocated up to the highest slot added so
        far. Nothing is printed outside the box: it grows (with :data:`_BOX_MARGIN_PX`) to take every
        footprint added, so the bits are those of the whole top view (:meth:`full_bits`), on the part's
        box only (a part of 40 x 40 mm on a 150 mm square: 1/14 of the memory).
    """

    def __init__(self, shape: tuple[int, int], layer_z, layer_height, fill_layers: int = 2) -> None:
        self.shape = (int(shape[0]), int(shape[1]))
        z = np.asarray(layer_z, np.float64).reshape(-1)
        lh = np.asarray(layer_height, np.float64).reshape(-1)
        lh = np.where(np.isfinite(lh) & (lh > 0), lh, 0.2)
        self.tops = np.unique(np.round(z[np.isfinite(z)], 4))
        # slots each layer fills: those whose top lies in (z - h, z]
        self._lo = np.searchsorted(self.tops, np.round(z - lh, 4) + 1e-6, side="left")
        self._hi = np.searchsorted(self.tops, np.round(z, 4), side="left")
        self.fill_layers = int(fill_layers)
        self.reset()

    def reset(self) -> None:
        """Forget every added layer (memory released)."""
        self.bits = np.zeros((0, 0, 0), np.uint8)
        self.origin = (0, 0)

    @property
    def max_nbytes(self) -> int:
        """Memory the bits reach once every slot is printed over the whole top view, bytes (the bound)."""
        H, W = self.shape
        return len(self.tops) * H * ((W + 7) // 8)

    @property
    def nbytes(self) -> int:
        """Memory held by the occupancy bits, bytes."""
        return int(self.bits.nbytes)

    def full_bits(self) -> np.ndarray:
        """The bits on the whole top view, shape (S_alloc, H, ceil(W / 8)), uint8 (a copy: for checks and tools)."""
        H, W = self.shape
        out = np.zeros((self.bits.shape[0], H, (W + 7) // 8), np.uint8)
        (r0, b0), (_, h, b) = self.origin, self.bits.shape
        out[:, r0:r0 + h, b0:b0 + b] = self.bits
        return out

    def _grow(self, n_slots: int) -> None:
        have = self.bits.shape[0]
        if n_slots <= have:
            return
        n = min(max(n_slots, 2 * have, 16), len(self.tops))
        grown = np.zeros((n, *self.bits.shape[1:]), np.uint8)
        grown[:have] = self.bits
        self.bits = grown

    def _cover(self, rows: tuple[int, int], byte_cols: tuple[int, int]) -> None:
        """Grow the box to take rows ``rows`` and bytes ``byte_cols`` (half-open), with the margin; bits kept."""
        (r0, b0), (S, h, b) = self.origin, self.bits.shape
        if h and b and r0 <= rows[0] and rows[1] <= r0 + h and b0 <= byte_cols[0] and byte_cols[1] <= b0 + b:
            return
        H, W = self.shape
        m = _BOX_MARGIN_PX
        lo_r, hi_r = (min(rows[0], r0), max(rows[1], r0 + h)) if h and b else rows
        lo_b, hi_b = (min(byte_cols[0], b0), max(byte_cols[1], b0 + b)) if h and b else byte_cols
        nr0, nr1 = max(lo_r - m, 0), min(hi_r + m, H)
        nb0, nb1 = max(lo_b - m // 8, 0), min(hi_b + m // 8, (W + 7) // 8)
        grown = np.zeros((S, nr1 - nr0, nb1 - nb0), np.uint8)
        if h and b:
            grown[:, r0 - nr0:r0 - nr0 + h, b0 - nb0:b0 - nb0 + b] = self.bits
        self.bits, self.origin = grown, (nr0, nb0)

    def add(self, layer: int, mask: np.ndarray) -> int | None:
        """Add the footprint of layer ``layer`` (bool (H, W)) to the slots it spans.

        Layers are added in print order; a slot's bits are the union of the
        layers printed in it.

        Returns
        -------
        int or None
            The lowest slot whose bits may have changed (the layer's own lowest, or a closed gap's);
            ``None`` when nothing was added.
        """
        lo, hi = int(self._lo[layer]), int(self._hi[layer])
        if hi >= len(self.tops) or not mask.any():
            return None
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        self._cover((int(rows[0]), int(rows[-1]) + 1), (int(cols[0]) // 8, int(cols[-1]) // 8 + 1))
        self._grow(hi + 1)
        (r0, b0), (_, h, b) = self.origin, self.bits.shape
        W = self.shape[1]
        packed = np.packbits(mask[r0:r0 + h, 8 * b0:min(8 * (b0 + b), W)], axis=1, bitorder="little")
        lo = min(lo, hi)
        lowest = lo
        self.bits[lo : hi + 1] |= packed
        for d in range(2, self.fill_layers + 2):  # close gaps of d - 1 slots below the layer
            if lo - d < 0:
                break
            both = packed & self.bits[lo - d]
            if both.any():
                self.bits[lo - d + 1 : lo] |= both
                lowest = min(lowest, lo - d + 1)
        return lowest


@njit(cache=True, inline="always")
def _bit(bits, r0, b0, s, xi, yi):
    """1 when slot ``s`` is printed at pixel ``(xi, yi)``, else 0 (outside the box, or a slot not allocated yet: empty)."""
    yy, bx = yi - r0, (xi >> 3) - b0
    if s >= bits.shape[0] or yy < 0 or yy >= bits.shape[1] or bx < 0 or bx >= bits.shape[2]:
        return 0
    return (bits[s, yy, bx] >> (xi & 7)) & 1


@njit(cache=True, inline="always")
def _solid(bits, r0, b0, tops, xi, yi, z):
    """1 when the point at pixel ``(xi, yi)`` and height ``z`` (mm) lies inside a printed bead, else 0."""
    return _bit(bits, r0, b0, np.searchsorted(tops, z - _Z_TOL), xi, yi)


@njit(cache=True)
def _facing(bits, r0, b0, tops, xi, yi, z, du, dv, L, H, W):
    """Cosine between the horizontal normal of the slot's occupancy at ``(xi, yi)`` and the ray.

    ``H``, ``W``: the top view's rows and its packed width in px (``8 ceil(W / 8)``), where the neighbours clamp.
    """
    xm, xp = max(xi - 1, 0), min(xi + 1, W - 1)
    ym, yp = max(yi - 1, 0), min(yi + 1, H - 1)
    s = np.searchsorted(tops, z - _Z_TOL)  # the four neighbours' slot: one search, not four
    gx = 1.0 * _bit(bits, r0, b0, s, xp, yi) - _bit(bits, r0, b0, s, xm, yi)
    gy = 1.0 * _bit(bits, r0, b0, s, xi, yp) - _bit(bits, r0, b0, s, xi, ym)
    g = math.sqrt(gx * gx + gy * gy)
    if g < 1e-9:
        return 1.0
    return max((gx * du + gy * dv) / (g * L), 0.0)


def clear_map(hmax: np.ndarray, skip_px: int, reach_px: int, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Pixels with nothing printed within ``reach_px`` (Chebyshev) and at least ``reach_px`` inside the square.

    Parameters
    ----------
    hmax : ndarray, shape (H, W), float32
        The height map dilated over squares of half-side ``skip_px`` (:func:`skip_map`).
    skip_px, reach_px : int
        Half-side of ``hmax``'s squares and the reach wanted (>= ``skip_px``), px.
    box : (int, int, int, int), optional
        ``(r0, r1, c0, c1)``: rows and columns outside which the height map is 0 (``hmax`` is 0 beyond it grown by
        ``skip_px``): only that part is eroded, the rest is bare (the whole erosion's values, as in
        :func:`skip_map`).

    Returns
    -------
    ndarray, shape (H, W), uint8
        1 where every height-map pixel within ``reach_px`` is 0 (the bed) and the square's border is
        farther than ``reach_px``, else 0.
    """
    grow = max(int(reach_px) - int(skip_px), 0)
    if box is None:
        bare = _bare(hmax, grow)
    else:  # bare beyond the box grown by both reaches; eroded within it (nothing printed: bare everywhere)
        bare = np.ones(hmax.shape, np.uint8)
        g = grown_box(box, int(skip_px) + grow + 1, hmax.shape)
        if g is not None:
            bare[g] = _bare(np.ascontiguousarray(hmax[g]), grow)
    r = int(reach_px)
    out = np.zeros_like(bare)
    H, W = bare.shape
    if H > 2 * r and W > 2 * r:
        out[r:H - r, r:W - r] = bare[r:H - r, r:W - r]
    return out


def _bare(hmax: np.ndarray, grow: int) -> np.ndarray:
    """1 where ``hmax`` is 0 within ``grow`` px (a square of half-side ``grow``: erosion of the bare pixels), uint8."""
    bare = (hmax <= 0.0).view(np.uint8)
    if grow:  # a square of half-side reach: the skip squares grown by the rest (erosion of the bare pixels)
        kernel = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)
        bare = np.asarray(cv2.erode(bare, kernel, borderType=cv2.BORDER_REPLICATE), np.uint8)
    return bare


def approach_reach_px(skip_px: float, step_px: float) -> int:
    """How far (px) a ray can still move sideways once a skip would take it below the bed, with margin.

    The skip covers ``skip_px / step_px`` steps; a ray that cannot skip is at most that many steps (and one
    more) above the bed, each ``step_px`` sideways, and its rounded pixel moves one more.
    """
    return int(math.ceil((math.ceil(skip_px / step_px) + 2) * step_px)) + 1


@njit(cache=True)
def _march_volume(height, hmax, skip_px, shaded, bed, bits, r0, b0, tops, cu, cv, cz, z, step_px, max_steps, look,
                  out, hit_z, clear):
    """Follow the camera ray through every top-view pixel into the occupancy volume.

    ``look`` = ``(wall_value, wall_ambient, line_contrast, layer_h, hidden_value, depth_scale,
    depth_dark)``; ``clear`` (uint8 (H, W), :func:`clear_map` with :func:`approach_reach_px`): a ray
    that can no longer skip (the skip would pass the bed) and stands on a clear pixel meets nothing
    but the bed before it: its last steps are taken without looking (the same steps, the same
    sample: the result is identical, bit for bit); the rest as in
    :func:`~layerwatch.render.camera_view._march`. ``bits``: :attr:`OccupancyStack.bits` at its ``origin``
    ``(r0, b0)``.
    """
    H, W = height.shape
    WB = (W + 7) // 8 * 8  # the packed rows' width, where a wall's neighbours clamp
    wall_value, wall_ambient, line_contrast, layer_h = look[0], look[1], look[2], look[3]
    hidden, depth_scale, depth_dark = look[4], look[5], look[6]
    jump = skip_px / step_px
    row_l, row_dx, row_dy, row_dz = np.empty(W), np.empty(W), np.empty(W), np.empty(W)
    for v in range(H):
        # each ray's length and step first, for the whole row: a loop without branches that the compiler
        # vectorises (the same operations, so the same values: IEEE square root, division and products are
        # correctly rounded however they are issued), and the march's chain of steps no longer waits on a
        # division and a square root per ray
        for u in range(W):
            du, dv = u - cu, v - cv
            L = math.sqrt(du * du + dv * dv)
            dt = step_px / L if L >= 1e-6 else 0.0
            row_l[u], row_dx[u], row_dy[u], row_dz[u] = L, du * dt, dv * dt, dt * (cz - z)
        for u in range(W):
            du, dv = u - cu, v - cv
            L = row_l[u]
            if L < 1e-6:  # looking straight down: the plane point itself
                out[v, u], hit_z[v, u] = shaded[v, u], height[v, u]
                continue
            dx, dy, dz = row_dx[u], row_dy[u], row_dz[u]
            x, y, zz = float(u), float(v), z
            val, hz = -1.0, 0.0
            k = 0
            while k < max_steps:
                xi, yi = int(x + 0.5), int(y + 0.5)
                if xi < 0 or yi < 0 or xi >= W or yi >= H:  # left the square: bed or unknown
                    val = bilinear(shaded, x, y)
                    break
                if k > 0 and hmax[yi, xi] < zz - jump * dz and zz - jump * dz > 0.0:
                    x, y, zz, k = x + dx * jump, y + dy * jump, zz - dz * jump, k + int(jump)
                    continue
                if clear[yi, xi] != 0 and zz - jump * dz <= 0.0:  # bare bed all the way down (docstring)
                    while k < max_steps and zz > 0.0:
                        x, y, zz, k = x + dx, y + dy, zz - dz, k + 1
                    val = bilinear(shaded, x, y)
                    break
                h = height[yi, xi]
                if h >= zz and _solid(bits, r0, b0, tops, xi, yi, zz) != 0:  # (below the bed: the first slot)
                    hz = zz
                    if k == 0 or h - zz <= 1.5 * dz:  # the column's top surface
                        val, hz = bilinear(shaded, x, y), h
                    elif _solid(bits, r0, b0, tops, xi, yi, zz + 1.5 * dz) != 0:  # entered through a side: a wall
                        facing = _facing(bits, r0, b0, tops, xi, yi, zz, du, dv, L, H, WB)
                        val = wall_light(facing, zz, layer_h, wall_value, wall_ambient, line_contrast)
                    else:  # a top surface under something higher (sill, floor seen through a window)
                        f = min((z - zz) / depth_scale, 1.0) if depth_scale > 0.0 else 1.0
                        val = hidden * (1.0 - depth_dark * f)
                    break
                if zz <= 0.0:  # the bed: bare (its shaded top view) or under an overhang (its albedo)
                    val = bilinear(shaded, x, y) if h <= 0.0 else bed[yi, xi]
                    break
                x, y, zz, k = x + dx, y + dy, zz - dz, k + 1
            if val < 0.0:  # max_depth_mm reached: what lies under the ray there
                val = bilinear(shaded, x, y)
                hz = height[min(max(int(y + 0.5), 0), H - 1), min(max(int(x + 0.5), 0), W - 1)]
            out[v, u], hit_z[v, u] = val, hz


def view_through_volume(
    height: np.ndarray,
    shaded: np.ndarray,
    volume: OccupancyStack,
    bed: np.ndarray,
    center_mm: np.ndarray,
    topview: TopView,
    z: float,
    *,
    look: WallLook = DEFAULT_LOOK,
    hidden_value: float = 0.7,
    depth_scale_mm: float = 0.6,
    depth_darkening: float = 0.2,
    printed_box: tuple[int, int, int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The scene as the camera sees it through the plane ``Z = z``, with what lies in windows and under overhangs.

    Parameters
    ----------
    height : ndarray, shape (H, W), float32
        Height map of the same layers (the envelope of ``volume``), mm.
    shaded : ndarray, shape (H, W), float32
        Shaded top view (albedo x light, 0-1).
    volume : OccupancyStack
        Occupancy of the layers printed so far.
    bed : ndarray, shape (H, W), float32
        Albedo of the bare bed (0-1): shown where a ray reaches the bed under printed material.
    center_mm : ndarray, shape (3,)
        Camera centre in bed mm; must lie above ``z``.
    topview : TopView
    z : float
        Height of the layer plane, mm.
    look : WallLook
        Walls and the ray march's step and depth bound, as in
        :func:`~layerwatch.render.camera_view.view_from_camera`.
    hidden_value : float
        Brightness (0-1) of a flat, lit top surface of the material.
    depth_scale_mm, depth_darkening : float
        A hidden top surface loses ``depth_darkening`` of its brightness at
        ``depth_scale_mm`` (or more) below ``z``, as lower layers do in the top view.
    printed_box : (int, int, int, int), optional
        ``(r0, r1, c0, c1)``: rows and columns outside which ``height`` is 0 (the renderer's printed box): the
        march's skip and clear maps are computed there only (:func:`skip_map`, :func:`clear_map`; the same maps).

    Returns
    -------
    image : ndarray, shape (H, W), float32
        What the camera sees through each point of the plane, 0-1.
    hit_z : ndarray, shape (H, W), float32
        Height of the surface each ray met, mm.

    Raises
    ------
    ValueError
        The camera centre is not finite or not above ``z``; ``bed`` or ``volume`` do not fit ``height``.
    """
    c, cu, cv, max_steps = ray_setup(center_mm, topview, z, look.step_px, look.max_depth_mm)
    h = np.ascontiguousarray(height, np.float32)
    if bed.shape != h.shape or volume.shape != h.shape:
        raise ValueError(f"bed {bed.shape} and volume {volume.shape} must have the height map's shape {h.shape}")
    s = np.ascontiguousarray(shaded, np.float32)
    out = np.empty_like(s)
    hit = np.empty_like(h)
    shading = np.array([look.wall_value, look.wall_ambient, look.wall_line_contrast, look.layer_height_mm,
                        hidden_value, depth_scale_mm, depth_darkening], np.float64)
    hmax = skip_map(h, SKIP_PX, printed_box)
    clear = clear_map(hmax, SKIP_PX, approach_reach_px(SKIP_PX, look.step_px), printed_box)
    r0, b0 = volume.origin
    _march_volume(h, hmax, float(SKIP_PX), s, np.ascontiguousarray(bed, np.float32), volume.bits, int(r0), int(b0),
                  volume.tops, cu, cv, float(c[2]), float(z), float(look.step_px), max_steps, shading, out, hit, clear)
    return out, hit
