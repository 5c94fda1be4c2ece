"""Fast per-layer warps of camera photos into the top view.

The photo is distorted; the plane homography of eq. (3) acts on undistorted
pixels. :class:`TopViewWarper` therefore precomputes, once per photo size, a
*distortion lookup*: a coarse grid over the undistorted image plane (with a
margin, so barrel-distorted corners are kept) holding the distorted source
pixel of every grid point. For a layer at height ``z`` the lookup is warped
by ``top_from_image(z)`` with :func:`cv2.warpPerspective`, which yields for
every top-view pixel its source pixel in the photo; the table is converted to
fixed point (``CV_16SC2``) and applied with :func:`cv2.remap`. Tables are
cached by ``z``. A 1920x1080 -> 600x600 warp costs a few milliseconds.

References
----------
Petsiuk & Pearce (2022), Section 2.3, eqs. (1)-(3).
"""

from __future__ import annotations

from collections import OrderedDict
from functools import lru_cache

import cv2
import numpy as np

from layerwatch.errors import WarpError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.homography import top_from_image
from layerwatch.geometry.topview import TopView

__all__ = ["TopViewWarper", "occlusion_hint", "check_image"]

_FAR = -1.0e4  # source coordinate that is outside every photo
#: lookup px kept around what the planes' warps read (:meth:`TopViewWarper.clear`): interpolation taps and the
#: fixed-point rounding of the source coordinates reach at most 1 px and 1/32 px beyond the read point
_CROP_PAD = 3
#: heights above the highest plane warped so far whose reads a kept lookup crop covers, mm (a print rises by
#: a layer a photo: the crop is made again every so many mm)
_CROP_RISE_MM = 5.0


def check_image(photo: np.ndarray, what: str = "photo") -> np.ndarray:
    """Validate a photo array: uint8/uint16 ``(h, w)`` or ``(h, w, 1|3|4)``; return it contiguous."""
    if not isinstance(photo, np.ndarray):
        raise WarpError(f"{what} must be a NumPy image array, got {type(photo).__name__}.")
    if photo.dtype not in (np.uint8, np.uint16, np.float32):
        raise WarpError(f"{what} has dtype {photo.dtype}; pass an 8-bit image (as cv2.imread gives).")
    if photo.ndim not in (2, 3) or (photo.ndim == 3 and photo.shape[2] not in (1, 3, 4)):
        raise WarpError(f"{what} has shape {photo.shape}; pass a (h, w) or (h, w, 3) image.")
    if min(photo.shape[:2]) < 16:
        raise WarpError(f"{what} is only {photo.shape[1]}x{photo.shape[0]} px; pass a real camera frame.")
    return np.ascontiguousarray(photo)


def _max_radius(dist: np.ndarray) -> float:
    """Largest normalised radius up to which the radial distortion is monotonic."""
    return _max_radius_of(tuple(float(v) for v in np.asarray(dist, np.float64).reshape(-1)[:8]))


@lru_cache(maxsize=64)
def _max_radius_of(dist: tuple[float, ...]) -> float:
    """:func:`_max_radius` of the coefficients ``dist`` (a camera's: the same every frame, computed once)."""
    d = np.zeros(8)
    d[: len(dist)] = dist
    k1, k2, _, _, k3, k4, k5, k6 = d
    r = np.linspace(0.0, 4.0, 4001)
    r2 = r * r
    f = r * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    bad = np.nonzero(np.diff(f) <= 0)[0]
    return float(r[bad[0]]) * 0.97 if len(bad) else float(r[-1])


class TopViewWarper:
    """Warp photos of a posed camera into the top view of any layer plane.

    Parameters
    ----------
    camera : CameraModel
        Calibrated camera with a bed pose. Photos of another resolution with
        the same aspect ratio are handled via :meth:`CameraModel.scaled_to`.
    topview : TopView
        Output geometry (600 x 600 px for the paper's defaults).
    step_px : float
        Spacing of the distortion lookup grid, undistorted px (2 is exact to
        about 0.1 px for webcam lenses).
    margin : float
        Extra lookup coverage beyond the image on each side, as a fraction of
        the image size.
    cache_size : int
        Number of per-``z`` remap tables kept.
    """

    def __init__(self, camera: CameraModel, topview: TopView, *, step_px: float = 4.0,
                 margin: float = 0.25, cache_size: int = 16) -> None:
        if not camera.has_pose:
            raise WarpError("the camera model has no bed pose; run `layerwatch calibrate --markers PHOTO`.")
        self.camera = camera
        self.topview = topview
        self.step_px = float(step_px)
        self.margin = float(margin)
        self.cache_size = int(cache_size)
        self._lookups: dict[tuple[int, int], tuple[CameraModel, np.ndarray, np.ndarray]] = {}
        self._folds: dict[tuple[int, int], np.ndarray] = {}  # the lookup's fold-back mask per size, bits (:meth:`_folded`)
        #: per size, the crop of the lookup kept past :meth:`clear`: ``(rows, cols, crop, lowest z, highest z)``
        self._crops: dict[tuple[int, int], tuple[slice, slice, np.ndarray, float, float]] = {}
        self._z_range: dict[tuple[int, int], tuple[float, float]] = {}  # heights warped per size since the lookup
        self._restored: dict[tuple[int, int], np.ndarray] = {}  # lookups made again from their crops, until clear
        self._maps: OrderedDict = OrderedDict()
        self._invalid: dict = {}
        self._grids: dict = {}  # the half-resolution grids of the cached tables (:meth:`keep_box`)
        #: one box of one plane kept past :meth:`clear` (:meth:`keep_box`): ``(key, box, coarse crop, its origin)``
        self._kept: tuple[tuple, tuple, np.ndarray, tuple[int, int]] | None = None

    # ------------------------------------------------------------ lookups
    def _geometry(self, size: tuple[int, int]) -> tuple[CameraModel, np.ndarray, tuple[int, int]]:
        """``(camera at size, S, (Lh, Lw))`` of the lookup of photos of ``size``."""
        cam = self.camera.scaled_to(size)
        w, h = size
        s, m = self.step_px, self.margin
        lw, lh = int(np.ceil(w * (1 + 2 * m) / s)) + 1, int(np.ceil(h * (1 + 2 * m) / s)) + 1
        S = np.array([[1 / s, 0, m * w / s], [0, 1 / s, m * h / s], [0, 0, 1.0]])
        return cam, S, (lh, lw)

    def _lookup_for(self, z: float, size: tuple[int, int]) -> tuple[CameraModel, np.ndarray, np.ndarray]:
        """:meth:`_lookup`, or the whole lookup again from the crop :meth:`clear` kept when the warp of plane ``z``
        reads only inside it (the rest far off: never read, so the warp is the whole lookup's, bit for bit)."""
        lo, hi = self._z_range.get(size, (z, z))
        self._z_range[size] = (min(lo, z), max(hi, z))
        kept = self._crops.get(size)
        if size in self._lookups or kept is None:
            return self._lookup(size)
        rows, cols, crop, _, _ = kept
        cam, S, shape = self._geometry(size)
        read = self._read_box(cam, S, shape, z)
        if read is None or not (rows.start <= read[0] and read[1] <= rows.stop and cols.start <= read[2]
                                and read[3] <= cols.stop):
            return self._lookup(size)  # (built whole, and kept whole until the next clear)
        lut = self._restored.get(size)
        if lut is None:  # (not in _lookups: a crop is only ever taken from a whole lookup)
            lut = np.full((*shape, 2), _FAR, np.float32)
            lut[rows, cols] = crop
            self._restored[size] = lut
        return cam, S, lut

    def _read_box(self, cam: CameraModel, S: np.ndarray, shape: tuple[int, int],
                  z: float) -> tuple[int, int, int, int] | None:
        """Lookup rows and columns ``(r0, r1, c0, c1)`` (half-open, clipped) that :meth:`_coarse` reads for plane
        ``z``, with :data:`_CROP_PAD`; ``None`` when the plane's horizon crosses the grid (read it whole).

        The grid's corners map into the lookup with a positive homogeneous coordinate, which is affine in
        the grid position, so positive over the whole grid: the grid maps onto the quadrilateral of its
        corners' images, whose box bounds every point read.
        """
        hh, ww = self.topview.shape
        ch, cw = (hh + 4) // 2 + 1, (ww + 4) // 2 + 1
        M = self._coarse_matrix(cam, S, z)
        corners = np.linalg.inv(M) @ np.array([[0, cw - 1, 0, cw - 1], [0, 0, ch - 1, ch - 1], [1.0, 1, 1, 1]])
        if not np.all(corners[2] > 1e-9) or not np.all(np.isfinite(corners)):
            return None
        x, y = corners[0] / corners[2], corners[1] / corners[2]
        lh, lw = shape
        r0, r1 = int(np.floor(y.min())) - _CROP_PAD, int(np.ceil(y.max())) + _CROP_PAD + 1
        c0, c1 = int(np.floor(x.min())) - _CROP_PAD, int(np.ceil(x.max())) + _CROP_PAD + 1
        return min(max(r0, 0), lh), min(max(r1, 0), lh), min(max(c0, 0), lw), min(max(c1, 0), lw)

    def _coarse_matrix(self, cam: CameraModel, S: np.ndarray, z: float) -> np.ndarray:
        """The matrix :meth:`_coarse` warps the lookup with (lookup px -> half-resolution grid px)."""
        D = np.array([[0.5, 0, 0.75], [0, 0.5, 0.75], [0, 0, 1.0]])
        return D @ top_from_image(cam, self.topview, z) @ np.linalg.inv(S)

    def _lookup(self, size: tuple[int, int]) -> tuple[CameraModel, np.ndarray, np.ndarray]:
        """``(camera at size, S, lookup (Lh, Lw, 2) float32)``; ``S`` maps undistorted px -> lookup px."""
        if size in self._lookups:
            return self._lookups[size]

        cam, S, (lh, lw) = self._geometry(size)
        w, h = size
        s, m = self.step_px, self.margin
        KL = S @ cam.K
        if np.any(cam.dist != 0):
            lut = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, KL, (lw, lh), cv2.CV_32FC2)[0]
            lut[self._folded(size, KL, cam.dist, (lh, lw))] = _FAR
        else:
            gx, gy = np.meshgrid(np.arange(lw, dtype=np.float32), np.arange(lh, dtype=np.float32))
            lut = np.stack([gx * s - m * w, gy * s - m * h], axis=-1).astype(np.float32)
        self._lookups[size] = (cam, S, lut)
        return self._lookups[size]

    def _folded(self, size: tuple[int, int], KL: np.ndarray, dist: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Lookup pixels beyond the monotonic radius, where the distortion polynomial folds back (never sampled).

        Bool (Lh, Lw). Kept per image size as bits (~37 kB at 1080p) past :meth:`clear`, unlike the lookup
        itself (2.3 MB): a farm printer rebuilds its lookup on every photo, and this mask (~0.7 ms of
        float64 temporaries) is the same every time.
        """
        packed = self._folds.get(size)
        if packed is None:
            lh, lw = shape
            # a row and a column broadcast: the same values as on the whole grid, without the grid
            gx, gy = np.arange(lw)[None, :], np.arange(lh)[:, None]
            Ki = np.linalg.inv(KL)
            nx = Ki[0, 0] * gx + Ki[0, 1] * gy + Ki[0, 2]
            ny = Ki[1, 1] * gy + Ki[1, 2]
            folded = nx * nx + ny * ny > _max_radius(dist) ** 2
            self._folds[size] = np.packbits(folded, axis=None)
            return folded
        return np.unpackbits(packed, count=shape[0] * shape[1]).view(bool).reshape(shape)

    def maps(self, z: float, image_size: tuple[int, int] | None = None):
        """Remap tables for plane ``z``: ``(map1 CV_16SC2, map2 CV_16UC1, valid bool (H, W))``.

        ``image_size`` is the photo's ``(width, height)`` (default: the
        camera's). ``valid`` marks top-view pixels whose source lies inside
        the photo and in front of the camera.
        """
        w, h = (int(v) for v in (image_size or self.camera.image_size))
        size = (w, h)
        key = self._key(z, size)
        hit = self._maps.get(key)
        if hit is not None:
            self._maps.move_to_end(key)
            return hit
        coarse = self._coarse(z, size)
        src, valid = self._finish(coarse, z, size)
        map1, map2 = cv2.convertMaps(src, None, cv2.CV_16SC2)  # type: ignore[call-overload]  # stub rejects map2=None, which OpenCV accepts
        self._invalid[key] = None if valid.all() else np.flatnonzero(~valid)
        self._grids[key] = coarse  # (for keep_box; dropped with the tables)
        out = (map1, map2, valid)
        self._maps[key] = out
        while len(self._maps) > self.cache_size:
            old = self._maps.popitem(last=False)[0]
            self._invalid.pop(old, None)
            self._grids.pop(old, None)
        return out

    def _coarse(self, z: float, size: tuple[int, int]) -> np.ndarray:
        """The table of plane ``z`` on the half-resolution grid (float32 (ch, cw, 2)), before :meth:`_finish`."""
        cam, S, lut = self._lookup_for(z, size)
        hh, ww = self.topview.shape
        # build the table on a half-resolution grid (coarse px a <-> top px 2a - 1.5, so
        # that every output pixel interpolates strictly inside it), then upsample:
        # both the homography and the distortion are smooth at this scale.
        ch, cw = (hh + 4) // 2 + 1, (ww + 4) // 2 + 1
        return np.asarray(cv2.warpPerspective(lut, self._coarse_matrix(cam, S, z), (cw, ch), flags=cv2.INTER_LINEAR,
                                              borderMode=cv2.BORDER_CONSTANT, borderValue=(_FAR, _FAR, 0, 0)))

    def _finish(self, coarse: np.ndarray, z: float, size: tuple[int, int],
                box: tuple[slice, slice] | None = None, at: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
        """The top-view table (float32 (H, W, 2), far off where not seen) and ``valid`` from the coarse grid.

        ``box`` (top-view rows and columns, bounds given): only those pixels, from ``coarse`` = the coarse
        grid's rows and columns from ``at`` on, covering the box and one coarse pixel around it
        (:meth:`keep_box`); upsampling by 2 reads the same two coarse pixels with the same weights as on
        the whole grid, so the values are the whole table's, bit for bit.
        """
        w, h = size
        hh, ww = self.topview.shape
        (r0, r1), (c0, c1) = ((0, hh), (0, ww)) if box is None else ((box[0].start, box[0].stop),
                                                                         (box[1].start, box[1].stop))
        ch, cw = coarse.shape[:2]
        up = cv2.resize(coarse, (2 * cw, 2 * ch), interpolation=cv2.INTER_LINEAR)
        oy, ox = 2 - 2 * at[0], 2 - 2 * at[1]  # top px v is row v + 2 of the whole upsampled grid
        src = up[r0 + oy:r1 + oy, c0 + ox:c1 + ox]
        valid = cv2.inRange(src, (0.0, 0.0), (w - 1.0, h - 1.0)) > 0
        cam = self._lookups[size][0] if size in self._lookups else self.camera.scaled_to(size)
        depth_ok = self._in_front(cam, z)
        if depth_ok is not None:
            depth_ok = depth_ok[r0:r1, c0:c1]
            src = src.copy()
            valid &= depth_ok
            src[~depth_ok] = _FAR
        return src, valid

    def _table(self, z: float, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Source pixel of every top-view pixel of plane ``z`` (float32 (H, W, 2), far off where not seen) and ``valid``."""
        return self._finish(self._coarse(z, size), z, size)

    def keep_box(self, z: float, box: tuple[slice, slice], image_size: tuple[int, int] | None = None) -> bool:
        """Keep what a later :meth:`warp` of the rows and columns ``box`` on the plane ``z`` needs (a check that
        warps the next photo on this plane), also past :meth:`clear`.

        Only one box is kept (the last one asked for): the crop of the plane's half-resolution grid that
        covers it (about 2 bytes per pixel of the box); the box's table is finished from it, bit for bit
        the whole table's (:meth:`_finish`), without building the plane's grid again.

        Returns
        -------
        bool
            Plane ``z``'s tables (at ``image_size``, the photo's ``(width, height)``) were cached and the box
            is kept; False when they were not (nothing kept; the box's warp builds its table).
        """
        w, h = (int(v) for v in (image_size or self.camera.image_size))
        key = self._key(z, (w, h))
        coarse = self._grids.get(key)
        hh, ww = self.topview.shape
        if coarse is None or any(sl.step not in (None, 1) for sl in box):
            return False
        (v0, v1), (u0, u1) = ((sl.start or 0, n if sl.stop is None else sl.stop) for sl, n in zip(box, (hh, ww),
                                                                                                   strict=True))
        if not (0 <= v0 < v1 <= hh and 0 <= u0 < u1 <= ww):
            return False
        # top px v is row v + 2 of the upsampled grid, which reads coarse rows (v + 1) // 2 and the next:
        # coarse rows (v0 + 1) // 2 to (v1 + 2) // 2 inclusive cover the box (clipped to the grid)
        ch, cw = coarse.shape[:2]
        a0, a1 = (v0 + 1) // 2, min((v1 + 2) // 2 + 1, ch)
        b0, b1 = (u0 + 1) // 2, min((u1 + 2) // 2 + 1, cw)
        crop = coarse[a0:a1, b0:b1].copy()  # C-ordered: contiguous, and not a view of the grid that clear() drops
        self._kept = (key, _box_key((slice(v0, v1), slice(u0, u1))), crop, (a0, b0))
        return True

    def clear(self, lookups: bool = False) -> None:
        """Drop the cached per-``z`` remap tables (about 2.4 MB each at 600 x 600 px).

        A farm keeps one warper per printer and every layer has its own height,
        so a table is never used again after its layer: it is released rather than
        held until the next layer replaces it. ``lookups`` drops the distortion
        lookup too (about 2.3 MB at 1080p), keeping only its crop that the warps of the heights asked for since
        it was built read, and of heights up to :data:`_CROP_RISE_MM` above them (~0.5 MB for a camera that
        sees the bed square in half its view): the next photo's lookup is the whole one again with the
        rest far off (never read: a warp that would read beyond the crop builds the lookup whole), ~0.2 ms
        instead of ~1 ms for the whole lookup (its fold-back mask is kept too, ~37 kB).
        """
        self._maps.clear()
        self._invalid.clear()
        self._grids.clear()
        if lookups:
            for size, (_, _, lut) in self._lookups.items():
                self._keep_crop(size, lut)
            self._lookups.clear()
            self._restored.clear()

    def _keep_crop(self, size: tuple[int, int], lut: np.ndarray) -> None:
        """Keep the crop of the whole lookup ``lut`` that the warps of the heights seen (and a rise) read."""
        zr = self._z_range.pop(size, None)
        if zr is None:
            return
        cam, S, shape = self._geometry(size)
        lo, hi = zr
        boxes = [self._read_box(cam, S, shape, z) for z in (lo, hi + _CROP_RISE_MM)]
        if any(b is None for b in boxes):
            self._crops.pop(size, None)
            return
        # a plane's grid corners move along straight lines (vertical lines of the bed, projected) as z goes from
        # ``lo`` to ``hi + rise``: the two ends' boxes bound every height in between
        r0, c0 = min(b[0] for b in boxes), min(b[2] for b in boxes)  # type: ignore[index]
        r1, c1 = max(b[1] for b in boxes), max(b[3] for b in boxes)  # type: ignore[index]
        self._crops[size] = (slice(r0, r1), slice(c0, c1), lut[r0:r1, c0:c1].copy(), lo, hi + _CROP_RISE_MM)

    def _in_front(self, cam: CameraModel, z: float) -> np.ndarray | None:
        """None when the whole top view is in front of the camera, else a bool mask."""
        R, t = cam.R, cam.pose[1]
        bed_from_top = self.topview.bed_from_top
        # camera depth is affine in the top-view pixel coordinates
        a = R[2, :2] @ bed_from_top[:2, :]
        a = a + np.array([0.0, 0.0, R[2, 2] * z + t[2]])
        hh, ww = self.topview.shape
        corners = np.array([[0, 0, 1], [ww - 1, 0, 1], [0, hh - 1, 1], [ww - 1, hh - 1, 1]], float)
        if np.all(corners @ a > 1.0):
            return None
        u, v = np.meshgrid(np.arange(ww), np.arange(hh))
        return (a[0] * u + a[1] * v + a[2]) > 1.0

    # -------------------------------------------------------------- warp
    def warp(self, photo: np.ndarray, z: float,
             box: tuple[slice, slice] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Warp a photo into the top view of the plane ``Z = z``.

        Parameters
        ----------
        photo : ndarray, uint8, shape (h, w) or (h, w, c)
            Camera frame (distorted, as captured). Any resolution with the
            calibration's aspect ratio.
        z : float
            Height of the layer's top surface, mm.
        box : (slice, slice), optional
            Only these rows and columns of the top view (``top[box]`` of the whole warp, pixel
            for pixel, for the cost of the box: a check that reads a part's surroundings). The
            table is not cached.

        Returns
        -------
        top : ndarray, uint8, shape (H, W) or (H, W, c)
            Top view (``topview.shape``, or the box's), 0 where the camera saw nothing.
        valid : ndarray, bool, shape (H, W)
            True where the top-view pixel was inside the photo.

        Raises
        ------
        WarpError
            Not an image, another aspect ratio than the calibration, no pose, a box with a step.
        """
        photo = check_image(photo)
        h, w = photo.shape[:2]
        if box is not None:
            return self._warp_box(photo, z, box)
        map1, map2, valid = self.maps(z, (w, h))
        top = cv2.remap(photo, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        bad = self._invalid.get(self._key(z, (w, h)))
        if bad is not None:  # partly seen: blank what the camera did not see (no border blends)
            top.reshape(len(valid.flat), -1)[bad] = 0
        return top, valid

    def _warp_box(self, photo: np.ndarray, z: float, box: tuple[slice, slice]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`warp` of the rows and columns ``box`` only (its table is the whole warp's, cropped)."""
        if any(sl.step not in (None, 1) for sl in box):
            raise WarpError(f"box {box} must be two slices without a step.")
        h, w = photo.shape[:2]
        key = self._key(z, (w, h))
        hit = self._maps.get(key)
        kept = self._kept
        if hit is not None:  # the whole table is cached anyway
            map1, map2, valid = (m[box] for m in hit)
        else:
            if kept is not None and kept[0] == key and kept[1] == _box_key(box):  # kept by keep_box
                src, valid = self._finish(kept[2], z, (w, h), box, kept[3])
            else:
                src, valid = self._table(z, (w, h))
                src, valid = src[box], valid[box]
            map1, map2 = cv2.convertMaps(np.ascontiguousarray(src), None, cv2.CV_16SC2)  # type: ignore[call-overload]  # as in maps()
        top = cv2.remap(photo, np.ascontiguousarray(map1), np.ascontiguousarray(map2), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        top[~valid] = 0  # as the whole warp blanks what the camera did not see
        return top, valid

    @staticmethod
    def _key(z, size):
        return (tuple(int(v) for v in size), round(float(z), 4))


def _box_key(box: tuple[slice, slice]) -> tuple:
    """A hashable, comparable form of a box of two slices."""
    return tuple((sl.start, sl.stop) for sl in box)


def occlusion_hint(camera: CameraModel, topview: TopView, z: float,
                   part_box_mm: tuple[float, float, float, float], part_height_mm: float) -> np.ndarray:
    """Top-view pixels of plane ``z`` hidden from the camera behind a tall part.

    The part is approximated by its bounding box ``(xmin, ymin, xmax, ymax)``
    (bed mm) from the bed up to ``part_height_mm``. A pixel is flagged when
    the straight line from its bed point at height ``z`` to the camera centre
    passes through that box (slab test) somewhere strictly between the two.

    Returns
    -------
    ndarray, bool, shape (H, W)
        True = probably occluded (far side of the part).
    """
    hh, ww = topview.shape
    u, v = np.meshgrid(np.arange(ww, dtype=np.float64), np.arange(hh, dtype=np.float64))
    xy = topview.to_mm(np.stack([u, v], axis=-1))
    P = np.concatenate([xy, np.full((hh, ww, 1), float(z))], axis=-1)
    C = camera.center_mm
    D = C - P
    lo = np.array([part_box_mm[0], part_box_mm[1], 0.0])
    hi = np.array([part_box_mm[2], part_box_mm[3], float(part_height_mm)])
    t0 = np.full((hh, ww), 1e-6)
    t1 = np.ones((hh, ww))
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            d = D[..., k]
            ta = (lo[k] - P[..., k]) / d
            tb = (hi[k] - P[..., k]) / d
            near, far = np.minimum(ta, tb), np.maximum(ta, tb)
            par = d == 0
            inside = (P[..., k] >= lo[k]) & (P[..., k] <= hi[k])
            near = np.where(par, np.where(inside, -np.inf, np.inf), near)
            far = np.where(par, np.where(inside, np.inf, -np.inf), far)
            t0 = np.maximum(t0, near)
            t1 = np.minimum(t1, far)
    return t0 < t1
