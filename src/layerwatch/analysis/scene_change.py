"""Image-space change detection beside the printed layer: the pure functions of the scene channel.

The camera is stationary, so everything it sees that the G-code does not
change between two photos must look the same up to light and noise. The
stateful model (:class:`layerwatch.pipeline.scene.SceneModel`) keeps an
*expected appearance* image ``E`` of the scene; this module computes, for one
photo:

1. **Predicted change** ``M_k`` (:func:`predicted_change`): the layer's printed
   footprint (top view, dilated by ``margin_mm``) projected into the camera
   image on the layer's bottom and top planes (its top surface and the wall
   band below it), through the calibrated camera with its lens distortion.
   Rays of the working image are intersected with each plane
   (:func:`image_rays`, :func:`plane_maps`, :func:`top_coords`: the bed point
   of a ray is linear in the plane's height), so the projection is exact for
   every plane, not only the bed.
2. **Photometric normalisation** (:func:`photometric_fit`): a smooth
   per-channel illumination ratio ``photo ~ ratio * E``, robust medians of
   the log ratio over coarse cells outside ``M_k``, median-smoothed over
   cells, so exposure drift, auto white balance, flicker and a light that
   moved a little do not count as change (a single global gain did not
   suffice on the simulator: its spot light moves between frames).
   Vignetting is fixed per pixel and so is in ``E``.
3. **Change blocks** (:func:`change_blocks`): the mean absolute residual
   ``|photo - min(ratio E, 255)|`` (channel mean, grey levels) per block of
   ``block_px`` px, scored where at least half the block is outside the
   printed body and on the observed square. A block changed when its score
   is above ``max(min_change, median + noise_k * 1.4826 MAD)`` of the
   frame's block scores (the threshold follows each frame's own noise) and,
   unless it is above ``SHADE_LIMIT`` times that, when a gain of its own
   does not explain it (the residual after the best per-block, per-channel
   gain is above the same kind of threshold): a moving
   shade or the edge of a lamp's cone changes brightness, strands and
   objects change texture.
4. **Clipped channels** (:func:`_censored_absdiff`): a channel the camera
   clipped (at :data:`SATURATED` or above) only says "this bright or
   brighter", so its residual is one-sided (a photo darker than a clipped
   ``E``, or brighter than the prediction where the photo clipped) and
   nothing where both clipped. A bright orange or yellow part under a lamp
   clips its red channel over its whole lit top; its green and blue still
   show an object lying there (issue 18's scenario ``s019``: a hex key on
   the plate beside the ring was on pixels left out whole as "saturated",
   so the series channel reported nothing). Only white glare (every channel
   clipped) is left out, by the caller.

Working image. The frame is reduced to ``working_px`` on its long side by
area averaging (a 1080p frame 3 x 3) and smoothed (Gaussian, sigma 0.7 px):
block statistics of 8 px ~ 2 mm do not need more, and it costs a few
milliseconds (``SceneObservation.timings_ms``).
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

import cv2
import numpy as np
from numba import njit
from scipy import ndimage

from layerwatch.analysis.area_reduce import area_resize
from layerwatch.analysis.block_masks import blocks_to_pixels, components
from layerwatch.analysis.result import Region
from layerwatch.analysis.settings import SceneSettings
from layerwatch.errors import AnalysisError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.geometry.warp import TopViewWarper

__all__ = ["ChangeMap", "change_blocks", "change_regions", "changed_beside", "channel_max", "channel_mean", "image_rays", "photometric_fit", "plane_coords", "plane_maps",
           "predicted_change", "rays_over", "to_working", "top_coords", "working_crop", "working_size", "working_to_top"]

#: log-ratio distance from its cell's mean beyond which a pixel is left out of the fit (~ 20 %)
OUTLIER_LOG = 0.2
#: a block scoring above this many thresholds changed whatever a local shade explains
SHADE_LIMIT = 3.0
#: grey level at and above which a pixel is taken as saturated (left out of the fit and the scores)
SATURATED = 250.0


def working_size(image_size: tuple[int, int], long_side: int) -> tuple[int, int]:
    """``(width, height)`` of the working image: the frame scaled to ``long_side`` px (never enlarged)."""
    w, h = (int(v) for v in image_size)
    f = min(1.0, float(long_side) / max(w, h))
    return max(1, int(round(w * f))), max(1, int(round(h * f)))


def to_working(photo: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A camera frame as the scene channel reads it.

    Parameters
    ----------
    photo : ndarray, uint8, shape (h, w) or (h, w, 3)
        Frame as captured (any size with the working image's aspect ratio).
    size : (int, int)
        Working ``(width, height)`` px.

    Returns
    -------
    ndarray, float32, shape (height, width, 3)
        Area-averaged and smoothed (sigma 0.7 px), grey levels 0-255.

    Raises
    ------
    AnalysisError
        Not a uint8 grey or colour image, or another aspect ratio.
    """
    arr = np.asarray(photo)
    if arr.dtype != np.uint8 or arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (3, 4)):
        raise AnalysisError(f"the scene channel needs a uint8 grey or colour frame, got {arr.dtype} {arr.shape}.")
    h, w = arr.shape[:2]
    if abs(w / h - size[0] / size[1]) > 0.01 * size[0] / size[1]:
        raise AnalysisError(f"frame is {w}x{h}, not the camera's aspect ratio; recalibrate at this resolution.")
    if arr.ndim == 2:
        arr = cv2.cvtColor(arr, cv2.COLOR_GRAY2BGR)
    elif arr.shape[2] == 4:
        arr = arr[..., :3]
    small = area_resize(arr, size) if (w, h) != tuple(size) else arr
    return cv2.GaussianBlur(small.astype(np.float32), (0, 0), 0.7)


#: working px beyond a pixel that :func:`to_working`'s blur reads (sigma 0.7: a 7-tap kernel)
WORKING_BLUR_REACH_PX = 3


def working_crop(photo: np.ndarray, size: tuple[int, int], box: tuple[slice, slice],
                 reach_px: int = WORKING_BLUR_REACH_PX) -> tuple[np.ndarray, tuple[int, int]]:
    """:func:`to_working` of the working pixels ``box`` grown by ``reach_px``, resizing and blurring only that.

    The frame is cut at ``box`` grown by ``reach_px`` and aligned to whole source pixels (the area resize
    then averages the same source pixels with the same weights), so on every pixel at least
    :data:`WORKING_BLUR_REACH_PX` inside the cut (``box`` itself when ``reach_px`` is at least that) the
    result is the whole-image one, bit for bit (tested). A cut that would reach the bottom or right edge
    of the working image, or a scale that aligns only every more than 8 px or differs between the axes,
    takes the whole image (OpenCV computes the last pixels of a row on another path, so a cut ending at
    the edge differs there by ~1e-5 grey levels).

    Parameters
    ----------
    photo : ndarray, uint8, shape (h, w) or (h, w, 3)
        Frame as captured.
    size : (int, int)
        Working ``(width, height)`` px.
    box : (slice, slice)
        Rows and columns of the working image (steps of 1, bounds within it).
    reach_px : int
        Working px around ``box`` that the caller reads too (a later filter's radius, plus the blur's).

    Returns
    -------
    image : ndarray, float32, shape (rows, cols, 3)
        ``to_working(photo, size)[rows, cols]`` of the cut.
    origin : (int, int)
        Working-image row and column of its first pixel.
    """
    arr = np.asarray(photo)
    W, H = size
    if arr.ndim < 2:
        return to_working(arr, size), (0, 0)  # (raises: not an image)
    fx, fy = Fraction(arr.shape[1], W), Fraction(arr.shape[0], H)
    if fx != fy or fx.denominator > 8:
        return to_working(arr, size), (0, 0)
    d = fx.denominator
    (r0, r1), (c0, c1) = ((s.start or 0, n if s.stop is None else s.stop) for s, n in zip(box, (H, W), strict=True))
    y0, x0 = max(0, (r0 - reach_px) // d * d), max(0, (c0 - reach_px) // d * d)
    y1, x1 = -(-(r1 + reach_px) // d) * d, -(-(c1 + reach_px) // d) * d
    if y1 >= H or x1 >= W:  # OpenCV filters a row's last pixels on another path: whole-image values only there
        return to_working(arr, size), (0, 0)
    crop = arr[int(y0 * fy):int(y1 * fy), int(x0 * fx):int(x1 * fx)]
    return to_working(crop, (x1 - x0, y1 - y0)), (y0, x0)


def image_rays(camera: CameraModel, size: tuple[int, int], rows: np.ndarray | None = None,
               cols: np.ndarray | None = None) -> np.ndarray:
    """Unit ray of every working-image pixel (or of a grid of them) in bed coordinates.

    Parameters
    ----------
    camera : CameraModel
        Posed camera (scaled to ``size``; the lens distortion is undone).
    size : (int, int)
        Working ``(width, height)`` px.
    rows, cols : ndarray of int, optional
        Pixel rows and columns of a grid to compute alone (default: the whole image). Each
        pixel's ray is undistorted, turned and normalised on its own, so a grid's rays are the
        whole image's ``[rows][:, cols]`` bit for bit (tested).

    Returns
    -------
    ndarray, float32, shape (len(rows), len(cols), 3); (height, width, 3) by default
        Directions ``d`` with the ray ``C + t d`` (``C``: ``camera.center_mm``).
    """
    cam = camera.scaled_to(size)
    w, h = size
    rows = np.arange(h) if rows is None else rows
    cols = np.arange(w) if cols is None else cols
    uv = np.stack(np.meshgrid(np.asarray(cols, np.float64), np.asarray(rows, np.float64)), -1)
    gh, gw = uv.shape[:2]
    n = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist).reshape(gh, gw, 2)
    d = np.concatenate([n, np.ones((gh, gw, 1))], -1) @ cam.R  # R^T applied to row vectors
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d.astype(np.float32)


def plane_maps(rays: np.ndarray, center_mm: np.ndarray, topview: TopView) -> tuple[np.ndarray, np.ndarray]:
    """Where each image pixel's ray meets the plane ``Z = z``, as ``A + z B`` (top-view px).

    Along a ray ``C + t d`` the bed point is linear in its height, so one
    pair of arrays gives the map of every plane with two fused operations
    (:func:`top_coords`).

    Returns
    -------
    A, B : ndarray, float32, shape (2, height, width)
        Top-view ``(u, v)`` of the ray on the plane ``z`` is ``A + z * B``;
        rays that do not go down towards the bed get ``A`` far outside the top view.
    """
    C = np.asarray(center_mm, np.float64)
    d = rays.astype(np.float64)
    down = d[..., 2] < -1e-6
    dz = np.where(down, d[..., 2], -1.0)
    T = topview.top_from_bed
    kx, ky = d[..., 0] / dz, d[..., 1] / dz  # bed xy per mm of height along the ray
    x0, y0 = C[0] - C[2] * kx, C[1] - C[2] * ky  # the ray's point on the bed (z = 0)
    A = np.stack([T[0, 0] * x0 + T[0, 2], T[1, 1] * y0 + T[1, 2]])
    B = np.stack([T[0, 0] * kx, T[1, 1] * ky])
    A[:, ~down] = -1e6
    B[:, ~down] = 0.0
    return A.astype(np.float32), B.astype(np.float32)


def top_coords(maps: tuple[np.ndarray, np.ndarray], z: float) -> tuple[np.ndarray, np.ndarray]:
    """Top-view ``(mapx, mapy)`` (float32, shape (height, width)) of every image pixel on the plane ``Z = z``.

    ``maps`` is :func:`plane_maps`; the result is ready for :func:`cv2.remap`.
    """
    A, B = maps
    z32 = np.float32(z)
    return A[0] + z32 * B[0], A[1] + z32 * B[1]


def plane_coords(maps: tuple[np.ndarray, np.ndarray], z: float,
                 coords: dict[float, tuple[np.ndarray, np.ndarray]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`top_coords` of the plane ``Z = z``, kept in ``coords`` (by height) for the next caller of that plane.

    A plane found in ``coords`` is not computed again; one that is not is computed and added (``None``: computed,
    not kept).
    """
    z = float(z)
    if coords is not None and z in coords:
        return coords[z]
    mx, my = top_coords(maps, z)
    if coords is not None:
        coords[z] = (mx, my)
    return mx, my


def rays_over(maps: tuple[np.ndarray, np.ndarray], rect_px: tuple[float, float, float, float],
              z0: float, z1: float) -> np.ndarray:
    """Pixels whose ray, between the heights ``z0`` and ``z1`` (mm), passes over a top-view rectangle.

    A pixel's ray meets the plane ``Z = z`` at ``A + z B`` (:func:`plane_maps`), a segment over
    the heights; it is kept when that segment crosses the rectangle (slab test per axis).

    Parameters
    ----------
    maps : (ndarray, ndarray)
        :func:`plane_maps` (or a crop of it), shape (2, h, w) each.
    rect_px : (float, float, float, float)
        Two opposite corners ``(u0, v0, u1, v1)``, top-view px.
    z0, z1 : float
        Heights of the segment's ends, mm.

    Returns
    -------
    ndarray, bool, shape (h, w)
    """
    A, B = maps
    h, w = A.shape[1:]
    lo_t, hi_t = np.zeros((h, w), np.float32), np.ones((h, w), np.float32)
    u0, v0, u1, v1 = rect_px
    for k, (a, b) in enumerate(((min(u0, u1), max(u0, u1)), (min(v0, v1), max(v0, v1)))):
        start, d = A[k] + np.float32(z0) * B[k], B[k] * np.float32(z1 - z0)  # the segment start + t d, t in [0, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (a - start) / d, (b - start) / d
        flat, inside = np.abs(d) < 1e-9, (start >= a) & (start <= b)
        lo_t = np.maximum(lo_t, np.where(flat, np.where(inside, 0.0, np.inf), np.minimum(t1, t2)))
        hi_t = np.minimum(hi_t, np.where(flat, np.where(inside, 1.0, -np.inf), np.maximum(t1, t2)))
    return lo_t <= hi_t


def _morph_near(mask: np.ndarray, se: np.ndarray, *, dilate: bool) -> np.ndarray:
    """``cv2.dilate``/``cv2.erode`` of a uint8 mask by ``se``, computed on the mask's bounding box only.

    The box is grown by the element's radius plus one pixel, so every output
    pixel inside it sees the same neighbourhood as on the whole image (zeros
    around the mask; the image border as cv2 treats it) and every pixel
    outside it is 0 either way: the result equals the whole-image operation.
    """
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    out = np.zeros_like(mask)
    if rows.size == 0:
        return out
    r = max(se.shape) // 2 + 1
    box = (slice(max(0, rows[0] - r), rows[-1] + r + 1), slice(max(0, cols[0] - r), cols[-1] + r + 1))
    roi = np.ascontiguousarray(mask[box])
    out[box] = cv2.dilate(roi, se) if dilate else cv2.erode(roi, se)
    return out


def predicted_change(
    footprint: np.ndarray,
    z_planes: np.ndarray,
    maps: tuple[np.ndarray, np.ndarray],
    topview: TopView,
    margin_mm: float,
    coords: dict[float, tuple[np.ndarray, np.ndarray]] | None = None,
) -> np.ndarray:
    """Where the camera image may change because the G-code printed ``footprint`` between the planes.

    Parameters
    ----------
    footprint : ndarray, bool, shape (H, W)
        Top-view footprint of a layer (``topview`` geometry).
    z_planes : ndarray, shape (P,)
        Planes the material spans, mm (the layer's bottom and top: its top
        surface and the wall band below it).
    maps : (A, B)
        :func:`plane_maps` of the working image.
    topview : TopView
    margin_mm : float
        Dilation of the footprint before the projection, mm; a negative
        margin erodes it (the inside of a top surface, away from its walls).
    coords : dict of float to (ndarray, ndarray), optional
        :func:`top_coords` of ``maps`` by plane height, for a caller that projects several
        footprints onto one plane: the planes found there are not computed again, the
        others are computed and added to it.

    Returns
    -------
    ndarray, bool, shape (height, width)
        Working-image mask.
    """
    fp = np.asarray(footprint, np.uint8)
    k = int(round(2 * abs(margin_mm) * topview.px_per_mm)) | 1
    if k > 1:
        fp = _morph_near(fp, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)), dilate=margin_mm > 0)
    out = np.zeros(maps[0].shape[1:], np.uint8)
    for z in (float(v) for v in np.asarray(z_planes, float).ravel()):
        mx, my = plane_coords(maps, z, coords)
        out |= np.asarray(cv2.remap(fp, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0),
                          np.uint8)
    return out.astype(bool)


def photometric_fit(photo: np.ndarray, expected: np.ndarray, usable: np.ndarray,
                    cell_px: int = 32, smooth_cells: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """The smooth illumination ratio ``photo / expected`` per channel, fitted robustly outside ``M_k``.

    Radiance is albedo times irradiance, and a camera's gamma keeps a product
    a product, so a change of light (exposure, white balance, flicker, a lamp
    that moved) multiplies the expected image by a *smooth* per-channel field.
    It is estimated in the log domain: the mean of
    ``log(1 + photo) - log(1 + expected)`` over the usable pixels of every
    ``cell_px`` cell (every second pixel), then again without the pixels
    more than ``OUTLIER_LOG`` from it (strands, objects); cells with less
    than a quarter usable take the frame's median, then a ``smooth_cells`` x
    ``smooth_cells`` median over cells (a failure covering a few cells does
    not bend the field), bilinear up to the image.

    Parameters
    ----------
    photo, expected : ndarray, float32, shape (h, w, 3)
        Working images, grey levels.
    usable : ndarray, bool, shape (h, w)
        Pixels that should not have changed (outside ``M_k``, on the observed
        square, not saturated).
    cell_px, smooth_cells : int

    Returns
    -------
    ratio : ndarray, float32, shape (h, w, 3)
        ``photo ~ ratio * expected``.
    gain : ndarray, float64, shape (3,)
        The frame's median ratio per channel (0 when fewer than 50 usable pixels).
    """
    h, w = usable.shape
    ok = np.ascontiguousarray(usable[::2, ::2]).astype(np.float32)
    if ok.sum() < 50:
        return np.ones((h, w, 3), np.float32), np.zeros(3)
    # the log ratio only on the box of the usable pixels: elsewhere every use below weighs it by 0
    # (``keep`` is 0 there), so 0 in its place gives the same field and gains, bit for bit
    rows, cols = np.flatnonzero(ok.any(axis=1)), np.flatnonzero(ok.any(axis=0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    inner = cv2.subtract(np.log1p(photo[::2, ::2][box]), np.log1p(expected[::2, ::2][box]))
    lr = np.zeros((*ok.shape, *inner.shape[2:]), inner.dtype)
    lr[box] = inner
    c = max(1, cell_px // 2)
    size = (-(-ok.shape[1] // c), -(-ok.shape[0] // c))  # cells (m, n)
    glob = np.array([np.median(lr[..., k][ok > 0]) for k in range(3)])
    keep = ok
    for _ in range(2):  # masked cell means, then again without the pixels far from them (the changes)
        frac = cv2.resize(keep, size, interpolation=cv2.INTER_AREA)
        mean = cv2.resize(lr * keep[..., None], size, interpolation=cv2.INTER_AREA) / np.maximum(frac, 1e-6)[..., None]
        mean = np.where((frac >= 0.25)[..., None], mean, glob).astype(np.float32)
        near = cv2.resize(mean, ok.shape[::-1], interpolation=cv2.INTER_NEAREST)
        keep = ok * (channel_max(np.abs(lr - near)) < OUTLIER_LOG).astype(np.float32)
    if smooth_cells > 1:
        mean = ndimage.median_filter(mean, size=(smooth_cells, smooth_cells, 1), mode="nearest")
    field = cv2.resize(mean, (size[0] * cell_px, size[1] * cell_px), interpolation=cv2.INTER_LINEAR)[:h, :w]
    field = np.ascontiguousarray(field, np.float32)
    return np.exp(field, out=field), np.exp(glob).astype(np.float64)  # in place: no second frame-sized array


@dataclass
class ChangeMap:
    """Change blocks of one photo against ``E`` (working-image geometry).

    Attributes
    ----------
    score : ndarray, float32, shape (n, m)
        Mean absolute residual per block, grey levels (0 where not scored).
    scored : ndarray, bool, shape (n, m)
        Blocks at least half usable (outside ``M_k``, on the observed square).
    changed : ndarray, bool, shape (n, m)
        Scored blocks above ``threshold``.
    threshold : float
        The frame's block threshold, grey levels.
    noise : float
        Robust spread of the block scores (1.4826 MAD), grey levels.
    block_px : int
    """

    score: np.ndarray
    scored: np.ndarray
    changed: np.ndarray
    threshold: float
    noise: float
    block_px: int

    @property
    def changed_share(self) -> float:
        """Changed blocks over scored blocks (0 when none scored)."""
        n = int(self.scored.sum())
        return float(self.changed.sum()) / n if n else 0.0

    def pixels(self, shape: tuple[int, int]) -> np.ndarray:
        """Changed blocks as a working-image mask of ``shape`` (h, w), bool."""
        return blocks_to_pixels(self.changed, self.block_px, shape, fill=False)


def channel_mean(img: np.ndarray) -> np.ndarray:
    """Mean over the three channels of a float32 (h, w, 3) image, float32 (h, w)."""
    return cv2.transform(img, np.full((1, 3), 1.0 / 3.0, np.float32))


def channel_max(img: np.ndarray) -> np.ndarray:
    """Largest of the three channels, (h, w) (element-wise: numpy's reduction over a 3-long axis is slow)."""
    return np.maximum(np.maximum(img[..., 0], img[..., 1]), img[..., 2])


def _block_mean(res: np.ndarray, okf: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """Mean of ``res`` over the usable pixels (``okf`` 0/1) of each block; ``frac``: their share per block."""
    m, n = frac.shape[::-1]
    sums = cv2.resize(res * okf, (m, n), interpolation=cv2.INTER_AREA)
    return np.where(frac > 0, sums / np.maximum(frac, 1e-6), 0.0).astype(np.float32)


def _noise_threshold(vals: np.ndarray, floor: float, k: float) -> tuple[float, float]:
    """``(max(floor, median + k * 1.4826 MAD), 1.4826 MAD)`` of the block scores ``vals``."""
    if vals.size == 0:
        return float(floor), 0.0
    med = float(np.median(vals))
    noise = float(1.4826 * np.median(np.abs(vals - med)))
    return max(float(floor), med + k * noise), noise


def _block_roi(usable: np.ndarray, b: int) -> tuple[slice, slice]:
    """Rows and columns of the blocks of ``b`` px that hold a usable pixel (block-aligned; empty when none)."""
    rows, cols = np.flatnonzero(usable.any(axis=1)), np.flatnonzero(usable.any(axis=0))
    if rows.size == 0:
        return slice(0, 0), slice(0, 0)
    return (slice(rows[0] // b * b, (rows[-1] // b + 1) * b), slice(cols[0] // b * b, (cols[-1] // b + 1) * b))


def _censored_absdiff(img: np.ndarray, pred: np.ndarray,
                      clipped: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> np.ndarray:
    """``|img - pred|`` per channel, where a clipped value only bounds the true one from below.

    A channel at :data:`SATURATED` or above says "this bright or brighter" (the camera clipped it), so
    the residual is the distance between what each side allows: clipped in the photo, only a photo
    brighter than the prediction counts (``max(img - pred, 0)``); clipped in ``E``, only a photo darker
    than it (``max(pred - img, 0)``: a blue object on an orange floor whose red channel was clipped);
    clipped in both, nothing.

    Parameters
    ----------
    img, pred : ndarray, float32, shape (h, w, 3)
        The photo and the prediction (``ratio * E``, clipped at 255), grey levels.
    clipped : (ndarray, ndarray, ndarray) or None
        ``(pixels, in_expected, in_photo)``: the flat indices (k,) of the pixels with a clipped channel
        and their clipped channels in ``E`` and in the photo, bool (k, 3); ``None`` when no channel is.
        Only those pixels are computed again (a lit orange top is a few per cent of the view).

    Returns
    -------
    ndarray, float32, shape (h, w, 3)
    """
    res = cv2.absdiff(img, pred)
    if clipped is None:
        return res
    px, in_expected, in_photo = clipped
    d = img.reshape(-1, 3)[px] - pred.reshape(-1, 3)[px]
    brighter = np.where(in_expected, 0.0, d)
    np.maximum(brighter, np.where(in_photo, 0.0, -d), out=brighter)
    res.reshape(-1, 3)[px] = np.maximum(brighter, 0.0)
    return res


@njit(cache=True)
def _unclipped_pass(img, expected, ratio, usable, in_expected, b, pred, res, sxy, syy):
    """:func:`_roi_scores`' per-pixel work in one pass, where no usable pixel has a clipped channel.

    ``pred = min(expected ratio, 255)``, ``res = |img - pred|`` (``cv2.absdiff``) and the block means of
    ``img pred ok`` and ``pred pred ok`` (``ok``: ``usable`` as 0/1), each the same float32 operation as
    NumPy's, each block's sum in OpenCV's area-fast order (``cv2.resize(..., INTER_AREA)`` by a whole
    factor: the block's values of a channel row by row, four at a time as ``((v0 + v1) + v2) + v3``, the
    rest one at a time, times ``1.f / b^2``). Returns True, leaving the outputs unfinished, at the first
    usable pixel with a channel at :data:`SATURATED` or above in ``img`` or set in ``in_expected`` (the
    caller then takes the general path). ``img``, ``expected``, ``ratio`` (h, w, 3) float32, ``usable`` (h, w)
    bool, ``in_expected`` (h, w, 3) bool, ``h`` and ``w`` multiples of ``b``; ``pred``, ``res`` (h, w, 3),
    ``sxy``, ``syy`` (h / b, w / b, 3) float32.
    """
    n, m = sxy.shape[0], sxy.shape[1]
    grouped = b * b // 4 * 4
    scale = np.float32(1.0) / np.float32(b * b)
    top, sat = np.float32(255.0), np.float32(SATURATED)
    gx = np.zeros(3, np.float32)  # a block's group sums and sums, per channel, of img pred ok and pred pred ok
    gy = np.zeros(3, np.float32)
    sx = np.zeros(3, np.float32)
    sy = np.zeros(3, np.float32)
    for i in range(n):
        for j in range(m):
            sx[:] = 0.0
            sy[:] = 0.0
            k = 0
            for y in range(i * b, (i + 1) * b):
                for x in range(j * b, (j + 1) * b):
                    ok = usable[y, x]
                    f = np.float32(1.0) if ok else np.float32(0.0)
                    for c in range(3):
                        v, p = img[y, x, c], expected[y, x, c] * ratio[y, x, c]
                        if p > top:  # np.minimum(pred, 255) (a NaN stays)
                            p = top
                        if ok and (v >= sat or in_expected[y, x, c]):
                            return True
                        pred[y, x, c], res[y, x, c] = p, abs(v - p)
                        a1, a2 = (v * p) * f, (p * p) * f
                        if k < grouped:
                            if k % 4 == 0:
                                gx[c], gy[c] = a1, a2
                            else:
                                gx[c], gy[c] = gx[c] + a1, gy[c] + a2
                            if k % 4 == 3:
                                sx[c], sy[c] = sx[c] + gx[c], sy[c] + gy[c]
                        else:
                            sx[c], sy[c] = sx[c] + a1, sy[c] + a2
                    k += 1
            for c in range(3):
                sxy[i, j, c], syy[i, j, c] = sx[c] * scale, sy[c] * scale
    return False


def _roi_scores(photo: np.ndarray, expected: np.ndarray, usable: np.ndarray, ratio: np.ndarray,
                b: int, expected_clipped: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block scores, scored blocks and shade-free scores of a block-aligned crop (:func:`change_blocks`).

    Without a clipped channel on a usable pixel (most frames) the residual, the prediction and the gain's
    sums come from one pass (:func:`_unclipped_pass`: the same values); otherwise as below, with the
    clipped channels' one-sided residuals.
    """
    h, w = usable.shape
    n, m = h // b, w // b
    img = np.ascontiguousarray(photo)
    okf = usable.astype(np.float32)
    frac = cv2.resize(okf, (m, n), interpolation=cv2.INTER_AREA)
    in_expected = expected >= SATURATED if expected_clipped is None else expected_clipped
    if b > 2 and img.dtype == expected.dtype == ratio.dtype == np.float32:
        pred, res = np.empty_like(img), np.empty_like(img)
        sxy, syy = np.empty((n, m, 3), np.float32), np.empty((n, m, 3), np.float32)
        if not _unclipped_pass(img, expected, ratio, usable, in_expected, b, pred, res, sxy, syy):
            score = _block_mean(channel_mean(res), okf, frac)
            g = cv2.resize(sxy / np.maximum(syy, 1e-6), (m * b, n * b), interpolation=cv2.INTER_NEAREST)
            shade_free = _block_mean(channel_mean(cv2.absdiff(img, g * pred)), okf, frac)
            return score, frac >= 0.5, shade_free
    pred = expected * ratio
    np.minimum(pred, 255.0, out=pred)  # the camera clips too
    in_photo = img >= SATURATED
    any_clip = channel_max(in_photo | in_expected) & usable  # (unusable pixels weigh 0 whatever their residual)
    okc = okf[..., None]
    clipped = None
    if any_clip.any():
        px = np.flatnonzero(any_clip)
        clipped = (px, in_expected.reshape(-1, 3)[px], in_photo.reshape(-1, 3)[px])
        okc = np.repeat(okc, 3, axis=2)
        okc.reshape(-1, 3)[px] = ~(clipped[1] | clipped[2])
    score = _block_mean(channel_mean(_censored_absdiff(img, pred, clipped)), okf, frac)
    # the same residual after the best gain per block and channel (clipped channels left out of the
    # gain's fit): what a local shade explains
    sxy = cv2.resize(img * pred * okc, (m, n), interpolation=cv2.INTER_AREA)
    syy = cv2.resize(pred * pred * okc, (m, n), interpolation=cv2.INTER_AREA)
    gain = sxy / np.maximum(syy, 1e-6)
    if clipped is not None:  # a channel clipped all over a block takes its other channels' gain (a shade is grey)
        fitted = syy > 1e-6
        other = (gain * fitted).sum(-1, keepdims=True) / np.maximum(fitted.sum(-1, keepdims=True), 1)
        gain = np.where(fitted, gain, np.where(fitted.any(-1, keepdims=True), other, 1.0)).astype(np.float32)
    g = cv2.resize(gain, (m * b, n * b), interpolation=cv2.INTER_NEAREST)
    shade_free = _block_mean(channel_mean(_censored_absdiff(img, g * pred, clipped)), okf, frac)
    return score, frac >= 0.5, shade_free


def change_blocks(photo: np.ndarray, expected: np.ndarray, usable: np.ndarray, ratio: np.ndarray,
                  settings: SceneSettings, expected_clipped: np.ndarray | None = None) -> ChangeMap:
    """Score every block of the photo against the normalised expected appearance.

    Parameters
    ----------
    photo, expected : ndarray, float32, shape (h, w, 3)
    usable : ndarray, bool, shape (h, w)
    ratio : ndarray, float32, shape (h, w, 3)
        :func:`photometric_fit`.
    settings : SceneSettings
        ``block_px``, ``noise_k``, ``min_change``.
    expected_clipped : ndarray, bool, shape (h, w, 3), optional
        Channels of ``expected`` whose value is only a lower bound (the camera clipped them);
        default: those at :data:`SATURATED` or above. A photo's channel at :data:`SATURATED` or
        above is clipped. Residuals on clipped channels are one-sided (:func:`_censored_absdiff`).

    Returns
    -------
    ChangeMap
    """
    b = int(settings.block_px)
    h, w = usable.shape
    n, m = h // b, w // b
    score, scored = np.zeros((n, m), np.float32), np.zeros((n, m), bool)
    shade_free = np.zeros((n, m), np.float32)
    rows, cols = _block_roi(usable[: n * b, : m * b], b)
    if rows.stop > rows.start and cols.stop > cols.start:  # only blocks with usable pixels can be scored
        blocks = (slice(rows.start // b, rows.stop // b), slice(cols.start // b, cols.stop // b))
        score[blocks], scored[blocks], shade_free[blocks] = _roi_scores(
            photo[rows, cols], expected[rows, cols], usable[rows, cols], ratio[rows, cols], b,
            None if expected_clipped is None else expected_clipped[rows, cols])
    threshold, noise = _noise_threshold(score[scored], settings.min_change, settings.noise_k)
    thr2, _ = _noise_threshold(shade_free[scored], settings.min_change, settings.noise_k)
    strong = score > SHADE_LIMIT * threshold
    changed = scored & (score > threshold) & (strong | (shade_free > thr2))
    return ChangeMap(score, scored, changed, threshold, noise, b)


def working_to_top(work: np.ndarray, warper: TopViewWarper, z: float, photo_size: tuple[int, int]) -> np.ndarray:
    """A working-image label map (uint8 (h, w), 0 = nothing) in the top view of the plane ``Z = z``.

    Scaled to the photo's size and warped with the pipeline's own top-view
    maps (the photo's homography and lens model), nearest neighbour, so the
    labels land where the warped photo shows the same pixels.

    Returns
    -------
    ndarray, uint8, shape (H, W)
        0 outside what the camera saw.
    """
    full = cv2.resize(np.asarray(work, np.uint8), photo_size, interpolation=cv2.INTER_NEAREST)
    map1, map2, _ = warper.maps(z, photo_size)
    return np.asarray(cv2.remap(full, map1, map2, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0),
                      np.uint8)


def change_regions(changed: np.ndarray, similarity: np.ndarray, topview: TopView,
                   min_area_mm2: float) -> list[Region]:
    """Connected changed areas of the top view as :class:`~layerwatch.analysis.result.Region` records.

    Parameters
    ----------
    changed : ndarray, bool, shape (H, W)
        Top-view pixels of changed blocks (outside the layer's predicted change).
    similarity : ndarray, float32, shape (H, W)
        Per pixel ``threshold / score`` of its block (below 1 = changed), 1 elsewhere.
    topview : TopView
    min_area_mm2 : float
        Smaller regions are dropped.

    Returns
    -------
    list of Region
        Largest first; ``outside_fraction`` 1, ``n_blocks`` the region's
        area in 2 x 2 mm blocks (rounded up).
    """
    n, lab, stats, (v0, u0) = components(changed)
    px_mm2 = 1.0 / topview.px_per_mm**2
    out: list[Region] = []
    for i in range(1, n):
        x, y, w, h, area_px = (int(v) for v in stats[i])
        area = area_px * px_mm2
        if area < min_area_mm2:
            continue
        sel = lab[y - v0 : y - v0 + h, x - u0 : x - u0 + w] == i
        sims = similarity[y : y + h, x : x + w][sel]
        vv, uu = np.nonzero(sel)
        (x0, y0), (x1, y1) = topview.to_mm(np.array([[x, y + h - 1], [x + w - 1, y]], float))  # v runs down
        cx, cy = topview.to_mm(np.array([uu.mean() + x, vv.mean() + y]))
        out.append(Region(area_mm2=float(area), bbox_mm=(float(x0), float(y0), float(x1), float(y1)),
                          centroid_mm=(float(cx), float(cy)), n_blocks=int(np.ceil(area / 4.0)),
                          mean_similarity=float(sims.mean()), min_similarity=float(sims.min()),
                          outside_fraction=1.0))
    out.sort(key=lambda r: -r.area_mm2)
    return out


def changed_beside(top: np.ndarray, bed_top: np.ndarray, footprint: np.ndarray, topview: TopView,
                   settings: SceneSettings) -> list[Region]:
    """Single-photo scene check in the top view: the photo against the empty bed beside the footprint.

    What ``layerwatch compare --bed-photo`` runs on one top view (no series,
    no camera): both images warped to the same top view, compared outside
    the footprint dilated by ``settings.margin_mm`` with the same photometric
    fit and change blocks as the series channel (blocks of
    ``settings.block_px`` top-view px). Lower layers and walls seen beside the
    top layer are not modelled here, so a tall part's own walls count as change.

    Parameters
    ----------
    top, bed_top : ndarray, uint8, shape (H, W) or (H, W, 3)
        Top views of the photo and of the empty bed.
    footprint : ndarray, bool, shape (H, W)
    topview : TopView
    settings : SceneSettings

    Returns
    -------
    list of Region
        Changed regions beside the footprint (bed mm), largest first.
    """
    size = (topview.shape[1], topview.shape[0])
    a, b = to_working(np.asarray(top), size), to_working(np.asarray(bed_top), size)
    k = int(round(2 * settings.margin_mm * topview.px_per_mm)) | 1
    near = cv2.dilate(np.asarray(footprint, np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0
    usable = ~near & (channel_max(a) > 0) & (channel_max(b) > 0) & (channel_max(a) < SATURATED)
    ratio, _ = photometric_fit(a, b, usable)
    ch = change_blocks(a, b, usable, ratio, settings)
    sim = np.where(ch.changed, np.minimum(1.0, ch.threshold / np.maximum(ch.score, 1e-6)), 1.0)
    sim_px = blocks_to_pixels(np.asarray(sim, np.float32), ch.block_px, topview.shape, fill=1.0)
    return change_regions(ch.pixels(topview.shape) & usable, sim_px, topview, settings.min_region_mm2)
