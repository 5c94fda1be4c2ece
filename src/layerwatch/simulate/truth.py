"""Ground truth of a simulated failure: what the camera sees that the plan does not show.

The truth of a failed photo is a mask in the top view of the top layer's plane
(the frame the pipeline warps each photo to). A pixel of it is *failed* when the
camera ray through that pixel first meets something the plan does not put
there, or meets something other than what the plan shows there:

* **seen, not merely present**: every mask is found by marching the pixel's
  ray from the camera centre through the simulator's height field
  (:func:`first_hit`), so what the part hides from the camera (an object on the
  bed behind it, the far walls of a moved part, the bottom of a hole under its
  rim) is not failure area;
* **a failure that stays is still counted**: the truth is drawn from the
  whole scene after layer ``i``, not from layer ``i``'s beads, so a hole cut
  on layer ``k`` and still open at ``k + 1``, or a strand draped on layer
  ``k``, is still truth on the next photo while the camera sees it;
* **nothing that was never printed counts**: the plan a scene is compared
  with is the simulator's own scene with the failure undone (holes filled
  with the beads that were removed, the moved part put back), not the
  G-code's nominal geometry, so a wall position the print never reached is
  neither failure nor plan.

One function per failure type: :func:`raised_object` (``foreign_body``,
``spaghetti``), :func:`detachment`, :func:`layer_shift`, :func:`patch`
(``infill_defect``, ``thin_wall``: on a part without thin walls the latter is
a *wall gap*, see :func:`layerwatch.simulate.failures.has_thin_walls`) and
:func:`nothing_extruded`.

All heights are mm above the bed, the height fields live on the simulator's
grid (``Sight.grid``), the masks on ``Sight.topview``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from layerwatch.geometry.topview import TopView
from layerwatch.simulate.raster import grid_params
from layerwatch.simulate.shade import _solid_at

__all__ = ["Sight", "Hits", "first_hit", "deeper", "differs", "raised_object", "detachment", "layer_shift", "patch",
           "nothing_extruded"]

#: A seen surface this much (in layer heights) lower than the plan's is a hole, a vacated place.
DEPTH_LAYERS = 0.5


@dataclass(frozen=True)
class Sight:
    """The camera and the frames of one photo's truth.

    Parameters
    ----------
    C : ndarray, shape (3,)
        Camera centre, bed mm.
    topview : TopView
        Frame of the masks; its plane is ``z`` (the top layer's).
    grid : TopView
        Frame of the height fields.
    z : float
        Height of the top view's plane, mm.
    """

    C: np.ndarray
    topview: TopView
    grid: TopView
    z: float


@dataclass(frozen=True)
class Hits:
    """Where each top-view pixel's camera ray first meets the scene.

    Attributes
    ----------
    z : ndarray, float32, shape topview.shape
        Height of the hit, mm (0: the bed; NaN: pixel not marched).
    cell : ndarray, int32, shape topview.shape + (2,)
        Grid cell ``(v, u)`` of the hit; ``(-1, -1)`` for the bed or a pixel not marched.
    """

    z: np.ndarray
    cell: np.ndarray

    def on(self, cells: np.ndarray) -> np.ndarray:
        """Pixels whose hit lies on a grid cell flagged in ``cells`` (bool, grid shape)."""
        v, u = self.cell[..., 0], self.cell[..., 1]
        ok = v >= 0
        out = np.zeros(self.z.shape, bool)
        out[ok] = cells[v[ok], u[ok]]
        return out


@njit(cache=True)
def _march(C, xs, ys, z_plane, h, gap, s, ux0, vy0, zmax, out_z, out_v, out_u):
    Hg, Wg = h.shape
    for k in range(xs.shape[0]):
        d0, d1, d2 = xs[k] - C[0], ys[k] - C[1], z_plane - C[2]
        n = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        d0, d1, d2 = d0 / n, d1 / n, d2 / n
        out_z[k], out_v[k], out_u[k] = 0.0, -1, -1
        if d2 > -1e-6:
            continue
        t_bed = C[2] / (-d2)
        t = max((C[2] - zmax) / (-d2), 0.0)
        dt = 0.7 / (s * max(np.sqrt(d0 * d0 + d1 * d1), 1e-3))
        z_prev = 1e9
        while t <= t_bed:
            x, y, z = C[0] + t * d0, C[1] + t * d1, C[2] + t * d2
            u = int(ux0 + s * x + 0.5)
            v = int(vy0 - s * y + 0.5)
            if 0 <= u < Wg and 0 <= v < Hg and h[v, u] > 0.0 and z <= h[v, u] and _solid_at(h, gap, v, u, z, z_prev):
                out_z[k], out_v[k], out_u[k] = min(h[v, u], max(z, 0.0)), v, u
                break
            z_prev = z
            t += dt


def first_hit(sight: Sight, h: np.ndarray, gap: np.ndarray | None, where: np.ndarray | None = None) -> Hits:
    """March the camera ray of each top-view pixel in ``where`` through height field ``h``.

    Parameters
    ----------
    sight : Sight
    h : ndarray, float32, shape sight.grid.shape
        Height field, mm.
    gap : ndarray, float32, shape sight.grid.shape + (2,), or None
        Per cell the empty interval ``(lo, hi)`` under printed material, mm (rays pass through it).
    where : ndarray, bool, shape sight.topview.shape, optional
        Pixels to march; default all.

    Returns
    -------
    Hits
        Steps of 0.7 grid cells, as the simulator's own ray caster; a hit's
        height is the sample's, capped by the cell's top.
    """
    tv = sight.topview
    if where is None:
        where = np.ones(tv.shape, bool)
    v, u = np.nonzero(where)
    xy = tv.to_mm(np.stack([u, v], -1).astype(np.float64)).reshape(-1, 2)
    n = len(u)
    hz, hv, hu = np.zeros(n), np.full(n, -1, np.int32), np.full(n, -1, np.int32)
    h = np.ascontiguousarray(h, np.float32)
    if gap is None:
        gap = np.zeros((*h.shape, 2), np.float32)
    zmax = float(h.max()) if h.size else 0.0
    if n and zmax > 0:
        s, ux0, vy0 = grid_params(sight.grid)
        _march(np.asarray(sight.C, np.float64), np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]),
               float(sight.z), h, np.ascontiguousarray(gap, np.float32), s, ux0, vy0, zmax, hz, hv, hu)
    z = np.full(tv.shape, np.nan, np.float32)
    cell = np.full((*tv.shape, 2), -1, np.int32)
    z[v, u] = hz
    cell[v, u, 0], cell[v, u, 1] = hv, hu
    return Hits(z, cell)


def deeper(seen: Hits, plan: Hits, tol_mm: float) -> np.ndarray:
    """Pixels where the scene is seen more than ``tol_mm`` lower than the plan (a hole, a vacated place)."""
    with np.errstate(invalid="ignore"):
        return np.nan_to_num(plan.z - seen.z, nan=0.0) > tol_mm


def differs(seen: Hits, plan: Hits, tol_mm: float) -> np.ndarray:
    """Pixels where the scene is seen more than ``tol_mm`` higher or lower than the plan."""
    with np.errstate(invalid="ignore"):
        return np.abs(np.nan_to_num(plan.z - seen.z, nan=0.0)) > tol_mm


#: Grey closing of a height field before comparing shapes, mm: fills the gaps of sparse infill (up to 3 mm, as the
#: failure typer's closed outline), not the gaps a part is designed with.
ENVELOPE_MM = 3.0


def _envelope(sight: Sight, h: np.ndarray) -> np.ndarray:
    """``h`` (grid shape, mm) closed by a disc of :data:`ENVELOPE_MM`: the part's shape without its bead texture."""
    k = int(round(ENVELOPE_MM * sight.grid.px_per_mm)) | 1
    return cv2.morphologyEx(np.ascontiguousarray(h, np.float32), cv2.MORPH_CLOSE,
                            cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))


def _reach(sight: Sight, cells: np.ndarray, lo: np.ndarray | float, hi: np.ndarray | float,
           grow_px: int = 2) -> np.ndarray:
    """Top-view pixels whose rays can meet grid ``cells`` between heights ``lo`` and ``hi`` (mm).

    The cells' centres at the bottom, middle and top, projected through the
    camera centre onto the top view's plane, closed and grown by ``grow_px``:
    the only pixels worth marching for a change confined to those cells.
    """
    tv = sight.topview
    v, u = np.nonzero(cells)
    out = np.zeros(tv.shape, np.uint8)
    if not len(u):
        return out.astype(bool)
    xy = sight.grid.to_mm(np.stack([u, v], -1).astype(np.float64))
    lo = np.broadcast_to(np.asarray(lo, np.float64), cells.shape)[v, u]
    hi = np.broadcast_to(np.asarray(hi, np.float64), cells.shape)[v, u]
    C = np.asarray(sight.C, np.float64)
    pts = []
    for z in (lo, 0.5 * (lo + hi), hi):
        k = (C[2] - sight.z) / np.maximum(C[2] - z, 1e-3)
        pts.append(C[:2] + (xy - C[:2]) * k[:, None])
    uv = np.round(tv.to_px(np.concatenate(pts))).astype(int)
    H, W = out.shape
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    out[uv[ok, 1], uv[ok, 0]] = 1
    size = 2 * grow_px + 3
    return cv2.dilate(cv2.morphologyEx(out, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)),
                      np.ones((size, size), np.uint8)).astype(bool)


def raised_object(sight: Sight, h: np.ndarray, gap: np.ndarray | None, before: np.ndarray) -> np.ndarray:
    """Truth of a ``foreign_body`` or ``spaghetti``: pixels whose ray first meets the object.

    Parameters
    ----------
    sight : Sight
    h : ndarray, float32, grid shape
        The scene with the object (and the rest of the plate), mm.
    gap : ndarray or None
        The scene's gaps (see :func:`first_hit`).
    before : ndarray, float32, grid shape
        The same scene without the object, mm.

    Returns
    -------
    ndarray, bool, shape sight.topview.shape
        The object where the camera sees it (its top and the sides facing the
        camera); what the part hides of it is not counted. Strands draped on
        earlier layers stay in ``h``, so they stay truth while seen.
    """
    raised = h > before + 1e-4
    seen = first_hit(sight, h, gap, _reach(sight, raised, before, h))
    with np.errstate(invalid="ignore"):
        above = seen.on(raised)
        v, u = seen.cell[..., 0], seen.cell[..., 1]
        above[above] = seen.z[above] > before[v[above], u[above]] + 1e-4
    return above


def detachment(sight: Sight, h: np.ndarray, gap: np.ndarray | None, moved: np.ndarray,
               plan: np.ndarray, plan_gap: np.ndarray | None, tol_mm: float) -> np.ndarray:
    """Truth of a ``detachment``: the moved part as seen, and where the part should be and is not.

    Parameters
    ----------
    sight : Sight
    h, gap : ndarray
        The scene with the part moved (skirt and a plate's other objects in place), grid shape.
    moved : ndarray, bool, grid shape
        Cells whose top is the moved part.
    plan, plan_gap : ndarray
        The same scene with the part where it was printed.
    tol_mm : float
        A surface seen this much lower than the plan's is a vacated place.

    Returns
    -------
    ndarray, bool, shape sight.topview.shape
        Every pixel whose ray first meets the moved part (its top and the walls
        facing the camera: all of it is out of place), plus the pixels where
        the plan shows the part and the camera now sees the bed (or a lower
        surface). The far walls of the moved part are hidden and not counted.
    """
    reach = _reach(sight, (h > 0) | (plan > 0), 0.0, np.maximum(h, plan))
    seen = first_hit(sight, h, gap, reach)
    was = first_hit(sight, plan, plan_gap, reach)
    return seen.on(moved) | deeper(seen, was, tol_mm)


def layer_shift(sight: Sight, h: np.ndarray, gap: np.ndarray | None, below: np.ndarray, z_below: float,
                offset_mm: np.ndarray, tol_mm: float) -> np.ndarray:
    """Truth of a ``layer_shift``: where the shifted layers make the scene look other than planned.

    Parameters
    ----------
    sight : Sight
    h, gap : ndarray
        The scene, grid shape; every layer from the onset on is printed ``offset_mm`` off.
    below : ndarray, float32, grid shape
        The scene before the first shifted layer, mm.
    z_below : float
        Top of the last layer printed before the shift, mm.
    offset_mm : ndarray, shape (2,)
        The shift, bed mm.
    tol_mm : float
        Height difference, mm, from which a seen surface differs from the plan's.

    Returns
    -------
    ndarray, bool, shape sight.topview.shape
        Pixels whose seen surface is more than ``tol_mm`` higher or lower than
        the plan's (the shifted block put back by ``-offset_mm`` on ``below``):
        the overhang and the walls of the shifted layers facing the camera, and
        the place they left. Where the shifted top covers the planned top the
        camera sees the same surface at the same height (a translated layer
        looks like the planned one): not counted; nor what the block hides.
        Both scenes are compared by their envelopes (:func:`_envelope`): the
        translated bead texture of a sparse top is not a difference of shape.
    """
    block = h > z_below + tol_mm
    s = sight.grid.px_per_mm
    M = np.array([[1, 0, -offset_mm[0] * s], [0, 1, offset_mm[1] * s]], np.float32)
    back = cv2.warpAffine(np.where(block, h, 0).astype(np.float32), M, h.shape[::-1], flags=cv2.INTER_NEAREST)
    plan = np.maximum(below, back)
    plan_gap = None
    if gap is not None:
        moved_gap = cv2.warpAffine(np.ascontiguousarray(gap), M, h.shape[::-1], flags=cv2.INTER_NEAREST)
        plan_gap = np.where((back > below)[..., None], moved_gap, gap).astype(np.float32)
    reach = _reach(sight, block | (back > 0), z_below, np.maximum(h, plan))
    return differs(first_hit(sight, _envelope(sight, h), gap, reach),
                   first_hit(sight, _envelope(sight, plan), plan_gap, reach), tol_mm)


def patch(sight: Sight, h: np.ndarray, gap: np.ndarray | None, plan: np.ndarray, tol_mm: float) -> np.ndarray:
    """Truth of an ``infill_defect`` or ``thin_wall`` (a wall gap where the part has no thin wall).

    Parameters
    ----------
    sight : Sight
    h, gap : ndarray
        The scene with the beads missing (or under-extruded) on every layer of the patch so far.
    plan : ndarray
        The same scene with those beads printed.
    tol_mm : float
        A surface seen this much lower than the plan's is a hole.

    Returns
    -------
    ndarray, bool, shape sight.topview.shape
        Pixels that see into the hole: deeper than the plan. A hole of an
        earlier layer the later ones left open is counted; one covered by
        later beads, or whose bottom the rim hides, is not.
    """
    filled = plan > h + 1e-4
    reach = _reach(sight, filled, h, plan)
    return deeper(first_hit(sight, h, gap, reach), first_hit(sight, plan, gap, reach), tol_mm)


def nothing_extruded(footprint: np.ndarray) -> np.ndarray:
    """Truth of ``nothing_extruded``: the footprint of the layer that was not printed (top view).

    The layer's top is missing wherever it would have been; it lies on the
    top view's plane, so nothing hides it. ``footprint``: bool, topview shape.
    """
    return footprint.astype(bool)
