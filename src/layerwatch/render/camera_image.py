"""The volume reference rendered once per camera pixel, incrementally, then warped onto each layer's plane.

:func:`~layerwatch.render.volume.view_through_volume` follows, for every
layer, the ray through every top-view pixel of *that layer's plane*: the
plane moves up with each layer, so every ray is new every layer and the whole
view is marched again (~20 ms a layer at 600 x 600 px).

The camera does not move and the printed volume only grows. :class:`CameraImageRays`
therefore marches the rays of a fixed grid of *camera* pixels (the undistorted
image, on the part's projected box) and keeps, per ray, the index of the first
sample that meets material (``uint16``; the top bit marks a ray that meets
none and ends on the bed or leaves the observed square). Every ray has fixed
samples: it starts at the top of the print (``z_top``) and descends
``dz = min(step_px * C_z / L, dz_max)`` mm per sample (``L``: the horizontal
distance, top-view px, from the camera's foot to where the ray meets the bed).
A point is solid exactly as in :mod:`~layerwatch.render.volume` (under the
height map and in a printed slot). Adding a layer only ever makes points solid
(bits are only set, heights only rise), and only in the columns the layer was
rasterised into, at heights above what was there (or above the lowest slot it
changed); so a ray's first hit after the layer is the smaller of its kept hit
and the first solid sample inside that box (:meth:`CameraImageRays.add`): only
the rays that cross the box are looked at, and only over that segment.

Per layer, :meth:`CameraImageRays.view` then shades every kept hit from the
current state (vectorised, no marching): what counts as a column's top, a wall
(lit from the slot's occupancy gradient, with layer lines), a hidden top
(darkened with its depth under the *current* layer plane) or the bed is decided
from the current height map and occupancy at the hit, with the same rules as
:func:`~layerwatch.render.volume.view_through_volume`; tops sample the current
shaded top view (whose depth darkening follows the current layer). The camera
image is brought onto the layer's plane with the plane's homography (eq. 3,
:func:`~layerwatch.geometry.homography.image_from_top`, the geometry the photo's
warp uses; the grid is undistorted, so the lens distortion the photo's warp undoes
is not needed). Top-view pixels whose ray misses the part's projected box see
only the bare bed: there the shaded top view is read where the ray meets the bed
(a scaling about the camera's foot).

The grid's scale is chosen so that its pixels are no coarser, on the part's box
(its bed and its top), than the top view's (``px_per_mm``).

References
----------
Petsiuk & Pearce (2022), Section 2.3, eqs. (1)-(3) (the plane homography) and
Section 2.4 (reference images from G-code).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.homography import image_from_top, top_from_image
from layerwatch.geometry.topview import TopView
from layerwatch.render.camera_view import bilinear, wall_light
from layerwatch.render.volume import OccupancyStack, _facing, _solid

__all__ = ["CameraImageRays"]

#: top bit of a kept hit: the ray met no material (its index is where it reached the bed or left the square)
_END = 0x8000
_IDX = 0x7FFF


@njit(cache=True, inline="always")
def _ray(G, i, j, cu, cv, cz, ztop, step, dzmax):
    """Start ``(sx, sy)`` (top-view px at ``z_top``), step ``(dx, dy, dz)`` and horizontal direction
    ``(du, dv)``, length ``L`` of grid ray ``(i, j)``."""
    X = G[0, 0] * j + G[0, 1] * i + G[0, 2]
    Y = G[1, 0] * j + G[1, 1] * i + G[1, 2]
    w = G[2, 0] * j + G[2, 1] * i + G[2, 2]
    du, dv = X / w - cu, Y / w - cv  # from the camera's foot to the ray's bed point, top-view px
    L = math.sqrt(du * du + dv * dv)
    f = (cz - ztop) / cz
    dz = dzmax if L * dzmax < step * cz else step * cz / L
    return cu + du * f, cv + dv * f, du * dz / cz, dv * dz / cz, dz, du, dv, max(L, 1e-9)


@njit(cache=True, inline="always")
def _gone(sx, sy, dx, dy, dz, ztop, k, H, W):
    """True when sample ``k`` lies out of the square or at or below the bed (monotonic in ``k``)."""
    xi, yi = int(sx + k * dx + 0.5), int(sy + k * dy + 0.5)
    return xi < 0 or yi < 0 or xi >= W or yi >= H or ztop - k * dz <= 0.0


@njit(cache=True)
def _ends(hits, i0, j0, G, cu, cv, cz, ztop, step, dzmax, H, W):
    """Where every ray of ``hits`` (rows from ``i0``, columns from ``j0``) ends in an empty volume (bed, or out of the square).

    The first sample of :func:`_gone` (a monotonic test): estimated from the ray's crossings of the bed and the
    square's edges (``int(x + 0.5)`` leaves ``[0, W)`` at ``x <= -1.5`` or ``x >= W - 0.5``), then settled by the
    test itself around the estimate, so that it is the sample a march step by step stops at.
    """
    gh, gw = hits.shape
    for i in range(gh):
        for j in range(gw):
            sx, sy, dx, dy, dz, du, dv, L = _ray(G, i0 + i, j0 + j, cu, cv, cz, ztop, step, dzmax)
            est = ztop / dz
            if dx > 1e-12:
                est = min(est, (W - 0.5 - sx) / dx)
            elif dx < -1e-12:
                est = min(est, (-1.5 - sx) / dx)
            if dy > 1e-12:
                est = min(est, (H - 0.5 - sy) / dy)
            elif dy < -1e-12:
                est = min(est, (-1.5 - sy) / dy)
            k = min(max(int(est) - 2, 0), _IDX)
            while k > 0 and _gone(sx, sy, dx, dy, dz, ztop, k - 1, H, W):
                k -= 1
            while k < _IDX and not _gone(sx, sy, dx, dy, dz, ztop, k, H, W):
                k += 1
            hits[i, j] = _END | k


@njit(cache=True, inline="always")
def _slab(t0, t1, s, inv, a, e):
    """``(t0, t1)`` narrowed to the samples ``k`` whose coordinate ``s + k / inv`` lies in ``[a, e]`` (``inv`` = 0:
    the coordinate does not move; empty, ``t0 > t1``, when it lies outside)."""
    if inv != 0.0:
        ta, tb = (a - s) * inv, (e - s) * inv
        return max(t0, min(ta, tb)), min(t1, max(ta, tb))
    if s < a or s > e:
        return 1.0, 0.0
    return t0, t1


@njit(cache=True)
def _update(hits, i0, i1, j0, j1, G, cu, cv, cz, ztop, step, dzmax, height, bits, r0, b0, tops, boxes, zlos, zhi):
    """First solid sample of the rays of grid rows ``i0:i1``, columns ``j0:j1`` inside the changed boxes.

    ``boxes`` (n, 4): ``(u0, u1, v0, v1)``, top-view px (half-open), each with its ``zlos[b]``: every
    point that became solid lies in a box, above its ``zlo`` and at most at ``zhi``. A ray's kept hit
    becomes the first solid sample before it (or at it, for a ray that met nothing) within a box; the
    range of samples looked at is grown by one at each end (only ever more samples, each tested in full).
    """
    H, W = height.shape
    for i in range(i0, i1):
        for j in range(j0, j1):
            sx, sy, dx, dy, dz, du, dv, L = _ray(G, i, j, cu, cv, cz, ztop, step, dzmax)
            idx = 1.0 / dz
            ix = 1.0 / dx if abs(dx) > 1e-12 else 0.0
            iy = 1.0 / dy if abs(dy) > 1e-12 else 0.0
            for b in range(boxes.shape[0]):
                hv = hits[i, j]
                last = (hv & _IDX) if hv & _END else (hv & _IDX) - 1
                t0, t1 = (ztop - zhi - dz) * idx, (ztop - zlos[b] + dz) * idx
                t0, t1 = _slab(t0, t1, sx, ix, boxes[b, 0] - 1.5, boxes[b, 1] + 0.5)
                t0, t1 = _slab(t0, t1, sy, iy, boxes[b, 2] - 1.5, boxes[b, 3] + 0.5)
                if t0 > t1:
                    continue
                ka = max(int(math.floor(t0)) - 1, 0)
                kb = min(int(math.ceil(t1)) + 1, last)
                for k in range(ka, kb + 1):
                    xi, yi = int(sx + k * dx + 0.5), int(sy + k * dy + 0.5)
                    if xi < 0 or yi < 0 or xi >= W or yi >= H:
                        continue
                    zz = ztop - k * dz
                    if height[yi, xi] >= zz and _solid(bits, r0, b0, tops, xi, yi, zz) != 0:
                        hits[i, j] = k
                        break


@njit(cache=True)
def _march_all(hits, i0, j0, G, cu, cv, cz, ztop, step, dzmax, height, bits, r0, b0, tops):
    """Every ray marched from the top of the print: the from-scratch render the incremental one must equal."""
    H, W = height.shape
    gh, gw = hits.shape
    for i in range(gh):
        for j in range(gw):
            sx, sy, dx, dy, dz, du, dv, L = _ray(G, i0 + i, j0 + j, cu, cv, cz, ztop, step, dzmax)
            k = 0
            hv = _END | _IDX
            while k < _IDX:
                xi, yi = int(sx + k * dx + 0.5), int(sy + k * dy + 0.5)
                zz = ztop - k * dz
                if xi < 0 or yi < 0 or xi >= W or yi >= H:
                    hv = _END | k
                    break
                if height[yi, xi] >= zz and _solid(bits, r0, b0, tops, xi, yi, zz) != 0:
                    hv = k
                    break
                if zz <= 0.0:
                    hv = _END | k
                    break
                k += 1
            hits[i, j] = hv


@njit(cache=True)
def _shade(hits, i0, j0, G, cu, cv, cz, ztop, step, dzmax, height, shaded, bed, bits, r0, b0, tops, z, look, out):
    """What each kept hit looks like under the current layer (see module notes); ``look`` as in :mod:`.volume`."""
    H, W = height.shape
    WB = (W + 7) // 8 * 8
    wall_value, wall_ambient, line_contrast, layer_h = look[0], look[1], look[2], look[3]
    hidden, depth_scale, depth_dark = look[4], look[5], look[6]
    gh, gw = hits.shape
    for i in range(gh):
        for j in range(gw):
            sx, sy, dx, dy, dz, du, dv, L = _ray(G, i0 + i, j0 + j, cu, cv, cz, ztop, step, dzmax)
            hv = hits[i, j]
            k = hv & _IDX
            x, y, zz = sx + k * dx, sy + k * dy, ztop - k * dz
            xi, yi = int(x + 0.5), int(y + 0.5)
            if hv & _END:
                if xi < 0 or yi < 0 or xi >= W or yi >= H:
                    out[i, j] = bilinear(shaded, x, y)  # out of the square
                elif height[yi, xi] <= 0.0:  # bare bed: where the ray meets it (the sample is up to a step below)
                    t = min(max(zz, -dz), 0.0) / dz
                    out[i, j] = bilinear(shaded, x + t * dx, y + t * dy)
                else:
                    out[i, j] = bed[yi, xi]  # the bed under an overhang or a bridge
                continue
            h = height[yi, xi]
            if k == 0 or h - zz <= 1.5 * dz:  # the column's top surface, where the ray meets it
                t = min(max(h - zz, 0.0), 1.5 * dz) / dz
                out[i, j] = bilinear(shaded, x - t * dx, y - t * dy)
            elif _solid(bits, r0, b0, tops, xi, yi, zz + 1.5 * dz) != 0:  # entered through a side: a wall
                facing = _facing(bits, r0, b0, tops, xi, yi, zz, du, dv, L, H, WB)
                out[i, j] = wall_light(facing, zz, layer_h, wall_value, wall_ambient, line_contrast)
            else:  # a top surface under something higher (sill, floor seen through a window)
                f = min((z - zz) / depth_scale, 1.0) if depth_scale > 0.0 else 1.0
                out[i, j] = hidden * (1.0 - depth_dark * f)


class CameraImageRays:
    """First hits of a fixed grid of camera rays into a growing occupancy volume (see module notes).

    Parameters
    ----------
    camera : CameraModel
        Calibrated camera with a bed pose (its ``K`` and pose; the grid is undistorted).
    topview : TopView
        Frame of the height map, the occupancy and the result.
    box_px : (int, int, int, int)
        ``(u0, u1, v0, v1)``: top-view columns and rows (half-open) that anything of the print can
        reach (the toolpath's extent with its beads).
    z_top : float
        Top of the print, mm (the rays start there).
    min_layer_mm : float
        Thinnest layer of the print, mm: a ray descends at most half of it per sample.
    step_px : float
        Largest horizontal step of a ray, top-view px.

    Attributes
    ----------
    hits : ndarray, shape (gh, gw), uint16
        Per ray of the grid: index of its first solid sample, or :data:`_END` | the sample where it
        reached the bed or left the square. The only per-pixel state kept (2 bytes a ray).
    scale : float
        Grid px per undistorted image px (chosen so that the grid is no coarser than the top view
        on the part's box).
    """

    def __init__(self, camera: CameraModel, topview: TopView, box_px: tuple[int, int, int, int], z_top: float,
                 min_layer_mm: float = 0.2, step_px: float = 0.75) -> None:
        if not camera.has_pose:
            raise ValueError("the camera model has no bed pose")
        c = np.asarray(camera.center_mm, np.float64)
        self.cz = float(c[2])
        self.z_top = float(z_top) + 1e-3
        if not self.cz > self.z_top:
            raise ValueError(f"the camera (z = {self.cz:.1f} mm) must be above the print (z = {z_top:.1f} mm)")
        self.camera, self.topview = camera, topview
        self.cu, self.cv = (float(v) for v in topview.to_px(c[:2]))
        self.step = float(step_px)
        self.dzmax = max(0.5 * float(min_layer_mm), 0.01)
        u0, u1, v0, v1 = (int(v) for v in box_px)
        corners = np.array([[u, v, 1.0] for u in (u0 - 1.0, u1 + 1.0) for v in (v0 - 1.0, v1 + 1.0)])
        img = []
        for zz in (0.0, self.z_top):
            q = corners @ image_from_top(camera, topview, zz).T
            img.append(q[:, :2] / q[:, 2:3])
        pts = np.concatenate(img)
        # the grid's scale: no coarser than the top view where the box is seen smallest (its far side)
        pb = np.c_[pts, np.ones(len(pts))]
        ppm = []
        for zz, part in ((0.0, pb[:4]), (self.z_top, pb[4:])):
            Ht = top_from_image(camera, topview, zz)
            for p in part:
                J = _jacobian(Ht, p)  # top px per image px
                ppm.append(math.sqrt(abs(np.linalg.det(J))))
        self.scale = float(min(max(max(ppm), 0.25), 8.0))
        s = self.scale
        x0, y0 = float(pts[:, 0].min()) - 2.0 / s, float(pts[:, 1].min()) - 2.0 / s
        gw = int(math.ceil((float(pts[:, 0].max()) + 2.0 / s - x0) * s)) + 1
        gh = int(math.ceil((float(pts[:, 1].max()) + 2.0 / s - y0) * s)) + 1
        #: grid px (j, i) -> undistorted image px
        self.A = np.array([[1.0 / s, 0.0, x0], [0.0, 1.0 / s, y0], [0.0, 0.0, 1.0]])
        self._A_inv = np.linalg.inv(self.A)
        G = top_from_image(camera, topview, 0.0) @ self.A  # grid px -> bed point, top-view px
        self.G = np.ascontiguousarray(G / G[2, 2], np.float64)
        self.shape = (gh, gw)
        #: what every kernel takes to rebuild a ray: ``(G, cu, cv, cz, z_top, step, dzmax)``
        self._ray_args: tuple[np.ndarray, float, float, float, float, float, float] = (
            self.G, self.cu, self.cv, self.cz, self.z_top, self.step, self.dzmax)
        self.reset()

    @property
    def nbytes(self) -> int:
        """Memory of the kept hits, bytes."""
        return int(self.hits.nbytes)

    def reset(self) -> None:
        """An empty volume: every ray ends on the bed or out of the square."""
        self.hits = np.empty(self.shape, np.uint16)
        H, W = self.topview.shape
        _ends(self.hits, 0, 0, *self._ray_args, H, W)

    def grid_box(self, box_px: tuple[int, int, int, int], zlo: float, zhi: float) -> tuple[int, int, int, int]:
        """Grid rows and columns ``(i0, i1, j0, j1)`` whose rays can cross the top-view box between ``zlo`` and ``zhi``."""
        u0, u1, v0, v1 = box_px
        corners = np.array([[u, v, 1.0] for u in (u0 - 2.0, u1 + 1.0) for v in (v0 - 2.0, v1 + 1.0)])
        pts = []
        for zz in (min(max(zlo, 0.0), self.z_top), min(max(zhi, 0.0), self.z_top)):
            q = corners @ (self._A_inv @ image_from_top(self.camera, self.topview, zz)).T
            pts.append(q[:, :2] / q[:, 2:3])
        p = np.concatenate(pts)
        gh, gw = self.shape
        j0, j1 = max(int(math.floor(p[:, 0].min())) - 2, 0), min(int(math.ceil(p[:, 0].max())) + 3, gw)
        i0, i1 = max(int(math.floor(p[:, 1].min())) - 2, 0), min(int(math.ceil(p[:, 1].max())) + 3, gh)
        return i0, max(i1, i0), j0, max(j1, j0)

    def add(self, height: np.ndarray, volume: OccupancyStack, boxes: list[tuple[int, int, int, int, float]],
            zhi: float) -> None:
        """Take material added inside ``boxes``: top-view px ``(u0, u1, v0, v1, zlo)``, heights in ``(zlo, zhi]``.

        Parameters
        ----------
        height : ndarray, shape (H, W), float32
            Height map after the change, mm.
        volume : OccupancyStack
            Occupancy after the change.
        boxes : list of (int, int, int, int, float)
            Columns and rows (half-open) and lower height bound (mm): every point that became solid
            lies in one of the boxes, above its bound.
        zhi : float
            Every point that became solid lies at most at ``zhi``, mm.
        """
        if not boxes:
            return
        grid = np.array([self.grid_box(b[:4], b[4], zhi) for b in boxes])
        i0, j0 = int(grid[:, 0].min()), int(grid[:, 2].min())
        i1, j1 = int(grid[:, 1].max()), int(grid[:, 3].max())
        if i1 <= i0 or j1 <= j0:
            return
        r0, b0 = volume.origin
        _update(self.hits, i0, i1, j0, j1, *self._ray_args, height, volume.bits, int(r0), int(b0), volume.tops,
                np.array([b[:4] for b in boxes], np.float64), np.array([b[4] for b in boxes], np.float64),
                float(zhi))

    def march_all(self, height: np.ndarray, volume: OccupancyStack) -> np.ndarray:
        """The hits of a from-scratch march of every ray through the current volume (checks: equals :attr:`hits`)."""
        out = np.empty(self.shape, np.uint16)
        r0, b0 = volume.origin
        _march_all(out, 0, 0, *self._ray_args, np.ascontiguousarray(height, np.float32), volume.bits,
                   int(r0), int(b0), volume.tops)
        return out

    def camera_image(self, height: np.ndarray, shaded: np.ndarray, bed: np.ndarray, volume: OccupancyStack,
                     z: float, look: np.ndarray, hits: np.ndarray | None = None) -> np.ndarray:
        """The grid's camera image under the layer at ``z`` (float32 (gh, gw), 0-1), from :attr:`hits` (or ``hits``)."""
        out = np.empty(self.shape, np.float32)
        r0, b0 = volume.origin
        _shade(self.hits if hits is None else hits, 0, 0, *self._ray_args, np.ascontiguousarray(height, np.float32),
               np.ascontiguousarray(shaded, np.float32), np.ascontiguousarray(bed, np.float32), volume.bits,
               int(r0), int(b0), volume.tops, float(z), np.asarray(look, np.float64), out)
        return out

    def view(self, height: np.ndarray, shaded: np.ndarray, bed: np.ndarray, volume: OccupancyStack, z: float,
             look: np.ndarray) -> np.ndarray:
        """The reference as the camera sees it, on the top view of the plane ``Z = z``.

        Parameters
        ----------
        height, shaded, bed : ndarray, shape (H, W), float32
            Height map (mm), shaded top view and bed albedo (0-1) of the layers so far.
        volume : OccupancyStack
        z : float
            Height of the layer plane, mm.
        look : ndarray, shape (7,)
            ``(wall_value, wall_ambient, line_contrast, layer_h, hidden_value, depth_scale, depth_dark)``.

        Returns
        -------
        ndarray, shape (H, W), float32
            What the camera sees through each point of the plane, 0-1.
        """
        cam = self.camera_image(height, shaded, bed, volume, z, look)
        H, W = self.topview.shape
        M = self._A_inv @ image_from_top(self.camera, self.topview, z)  # top px of plane z -> grid px
        # rays that miss the part's box: the bare bed where they meet it (a scaling about the camera's foot) ...
        f = self.cz / (self.cz - z)
        aff = np.array([[f, 0.0, self.cu * (1 - f)], [0.0, f, self.cv * (1 - f)]])
        img = cv2.warpAffine(np.ascontiguousarray(shaded, np.float32), aff, (W, H),
                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
        # ... the rest from the camera image (pixels whose source lies in the grid; the others are left)
        cv2.warpPerspective(cam, M, (W, H), dst=img, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_TRANSPARENT)
        return img


def _jacobian(Hm: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Jacobian (2, 2) of the homography ``Hm`` at the homogeneous point ``p``."""
    q = Hm @ p
    w = q[2]
    return (Hm[:2, :2] * w - np.outer(q[:2], Hm[2, :2])) / (w * w)
