"""Detection of the bed markers in a camera photo.

Two kinds (``MarkerSettings.kind``):

* ``"dots"``: white discs on a darker bed. A white top-hat (rectangular
  kernel, a few percent of the image) removes glare and slow shading; the
  bright residue is thresholded (Otsu, with a minimum contrast) and every
  contour is scored for circularity, solidity and contrast. Centres are the
  centroids of a sub-pixel *coverage* estimate at full resolution, i.e. the
  area centroids of the imaged discs (:mod:`~layerwatch.geometry.pose`
  corrects their small perspective bias). Which four of the candidates are
  the markers, and in which order, is decided by the pose solver.
* ``"aruco"``: ArUco tags (``cv2.aruco.ArucoDetector``); tag ``i`` sits at
  ``positions_mm[i]`` and its centre is the intersection of its diagonals
  (exact under perspective), so the order is given by the ids.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from layerwatch.errors import MarkerError
from layerwatch.geometry.warp import check_image
from layerwatch.percentile import lerp, linear_index, ranked_u8

__all__ = ["Blob", "confirm_dots", "detect_dots", "detect_aruco", "photo_problem", "to_grey"]


@dataclass(frozen=True)
class Blob:
    """A marker candidate: ``center`` (u, v) px, ``area`` px², quality ``score`` (higher is better)."""

    center: tuple[float, float]
    area: float
    circularity: float
    contrast: float
    score: float


def to_grey(photo: np.ndarray) -> np.ndarray:
    """uint8 grey image ``(h, w)`` of a BGR/grey photo (uint8 or uint16)."""
    img = check_image(photo)
    if img.dtype != np.uint8:
        img = cv2.normalize(img.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)  # type: ignore[call-overload]  # stub rejects dst=None, which OpenCV accepts
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY) if img.shape[2] >= 3 else img[..., 0]
    return np.ascontiguousarray(img)


def photo_problem(photo: np.ndarray) -> str | None:
    """A short reason why a photo is unusable (overexposed, dark, blurred, flat), or None."""
    g = to_grey(photo)
    small = cv2.resize(g, (320, max(1, int(320 * g.shape[0] / g.shape[1]))), interpolation=cv2.INTER_AREA)
    if np.mean(small >= 250) > 0.4:
        return "the photo is overexposed (most pixels are white); lower the exposure or light"
    if np.percentile(small, 99) < 40:
        return "the photo is too dark; add light or raise the exposure"
    if small.std() < 3:
        return "the photo is almost uniform; check the camera feed"
    lap = cv2.Laplacian(small, cv2.CV_32F)
    if float(lap.var()) < 4.0:
        return "the photo is badly blurred; refocus the camera"
    return None


def _median(values: np.ndarray) -> float:
    """:func:`numpy.median` of a flat uint8 array taken as float32, bit for bit (the mean of the middle one or
    two values, in float32: exact for integers), from its counts (:func:`~layerwatch.percentile.ranked_u8`)."""
    n = values.size
    ks = [n // 2 - 1, n // 2] if n % 2 == 0 else [(n - 1) // 2]
    mid = ranked_u8(values, ks).astype(np.float32)
    return float(mid[0] if len(mid) == 1 else (mid[0] + mid[1]) / np.float32(2))


def _percentile(values: np.ndarray, q: float) -> float:
    """:func:`numpy.percentile` (linear) of a uint8 array taken as float32, bit for bit, for a Python-float ``q``.

    numpy's steps (:mod:`layerwatch.percentile`) on the two order statistics it needs, in float32.
    """
    lo, hi, t = linear_index(values.size, q)
    a, b = ranked_u8(values, [lo, hi]).astype(np.float32)
    return lerp(a, b, t)


def _nearest_label(lab: np.ndarray, cy: float, cx: float) -> int:
    """The label of the labelled pixel (``lab > 0``) nearest to ``(cy, cx)``, the first in row-major order
    among equally near ones: ``lab[yy, xx][argmin((yy - cy)**2 + (xx - cx)**2)]`` over ``np.nonzero(lab)``.

    Looked for in a window around the point, doubled until the nearest pixel in it is nearer than any pixel
    outside it can be (a strict bound: no tie outside); distances are those of the whole image (halves of
    integers, squared exactly), and the window's row-major order is the image's, so the same pixel is chosen.
    ``lab`` must hold a labelled pixel.
    """
    H, W = lab.shape
    r = 8
    while True:
        r0, r1 = min(max(int(np.floor(cy)) - r, 0), H), min(max(int(np.ceil(cy)) + r + 1, 0), H)
        c0, c1 = min(max(int(np.floor(cx)) - r, 0), W), min(max(int(np.ceil(cx)) + r + 1, 0), W)
        whole = r0 == 0 and c0 == 0 and r1 == H and c1 == W
        yy, xx = np.nonzero(lab[r0:r1, c0:c1])
        if yy.size:
            yy, xx = yy + r0, xx + c0
            d = (yy - cy) ** 2 + (xx - cx) ** 2
            i = int(np.argmin(d))
            # a pixel outside the window is at least this far, in rows or in columns
            gap = min(cy - (r0 - 1) if r0 > 0 else np.inf, r1 - cy if r1 < H else np.inf,
                      cx - (c0 - 1) if c0 > 0 else np.inf, c1 - cx if c1 < W else np.inf)
            if whole or d[i] < gap * gap:
                return int(lab[yy[i], xx[i]])
        elif whole:
            raise ValueError("no labelled pixel")
        r *= 2


def _refine(grey: np.ndarray, box: tuple[int, int, int, int]) -> tuple[float, float, float] | None:
    """Coverage centroid ``(u, v, area)`` of the bright blob in ``box`` (x, y, w, h) at full resolution.

    ``grey``: uint8 (:func:`to_grey`). The background's median and the 99.5th percentile are read from the
    box's grey-level counts (the figures of :func:`numpy.median` and :func:`numpy.percentile` of its float32
    copy, bit for bit; tested), the blob is the component nearest the box's centre (:func:`_nearest_label`),
    and the centroid's coordinates are broadcast rows and columns instead of full grids (the same products and
    sums).
    """
    x, y, w, h = box
    H, W = grey.shape
    pad = max(3, int(0.6 * max(w, h)))
    x0, y0, x1, y1 = max(x - pad, 0), max(y - pad, 0), min(x + w + pad, W), min(y + h + pad, H)
    cut = grey[y0:y1, x0:x1]
    bg = _median(np.concatenate([cut[0], cut[-1], cut[:, 0], cut[:, -1]]))
    peak = _percentile(cut, 99.5)
    if peak - bg < 20:
        return None
    roi = cut.astype(np.float32)
    cov = np.clip((roi - bg) / (peak - bg) * 1.15 - 0.075, 0.0, 1.0)  # soft background floor

    # keep only the component under the candidate (neighbours and texture out)
    n, lab = cv2.connectedComponents((cov > 0.5).astype(np.uint8))
    if n < 2:
        return None
    k = _nearest_label(lab, y + h / 2 - y0, x + w / 2 - x0)
    keep = cv2.dilate((lab == k).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    cov = np.where(keep, cov, 0.0)
    s = float(cov.sum())
    if s <= 0:
        return None
    gy, gx = np.arange(roi.shape[0])[:, None], np.arange(roi.shape[1])[None, :]
    return float((cov * gx).sum() / s + x0), float((cov * gy).sum() / s + y0), s


def _score_contour(c, grey, tophat, f, k) -> Blob | None:
    """A :class:`Blob` for one contour of the thresholded top-hat, or None when it is no dot."""
    area = cv2.contourArea(c)
    if area < 6 or area > 0.6 * k * k:
        return None
    per = cv2.arcLength(c, True)
    circ = 4 * np.pi * area / max(per * per, 1e-9)
    hull = cv2.contourArea(cv2.convexHull(c))
    solidity = area / max(hull, 1e-9)
    if circ < 0.6 or solidity < 0.85:
        return None
    if len(c) >= 5:
        (_, _), (a, b), _ = cv2.fitEllipse(c)
        if min(a, b) <= 0 or max(a, b) / min(a, b) > 5:
            return None
    x, y, w, h = cv2.boundingRect(c)
    mask = np.zeros((h, w), np.uint8)
    cv2.drawContours(mask, [c - [x, y]], -1, 1, -1)
    contrast = float(tophat[y : y + h, x : x + w][mask > 0].mean())
    box = (int(x / f), int(y / f), int(np.ceil(w / f)), int(np.ceil(h / f)))
    ref = _refine(grey, box)
    if ref is None:
        return None
    score = min(circ, 1.0) * solidity * min(contrast / 100.0, 1.5)
    return Blob((ref[0], ref[1]), ref[2], float(circ), contrast, float(score))


def detect_dots(photo: np.ndarray, *, max_candidates: int = 12, min_contrast: float = 35.0,
                max_side_px: int = 1280) -> list[Blob]:
    """Find bright circular blobs (white dot markers).

    Parameters
    ----------
    photo : ndarray, uint8, shape (h, w) or (h, w, 3)
        BGR or grey camera frame.
    max_candidates : int
        At most this many blobs are returned, best first.
    min_contrast : float
        Minimum brightness above the local background, grey levels.
    max_side_px : int
        Detection runs on a copy downscaled to this longest side; centres are
        refined at full resolution.

    Returns
    -------
    list of Blob
        Sorted by decreasing ``score``; may be empty.
    """
    grey = to_grey(photo)
    H, W = grey.shape
    f = min(1.0, max_side_px / max(H, W))
    work = cv2.resize(grey, (int(W * f), int(H * f)), interpolation=cv2.INTER_AREA) if f < 1 else grey
    k = int(max(9, 0.12 * min(work.shape))) | 1
    tophat = cv2.morphologyEx(work, cv2.MORPH_TOPHAT, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    # several thresholds (as in a blob detector): a dot sitting in glare only separates
    # from the glare's residue at a high level, a dim dot only shows at a low one
    top = float(tophat.max())
    levels = [lv for lv in (min_contrast, 60.0, 90.0, 130.0, 180.0) if lv < top - 10] or [min_contrast]
    blobs: list[Blob] = []
    for level in levels:
        bw = (tophat > level).astype(np.uint8)
        contours, _ = cv2.findContours(bw, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if len(contours) > 2000:  # texture, not markers: a higher level will do
            continue
        for c in contours:
            blob = _score_contour(c, grey, tophat, f, k)
            if blob is None:
                continue
            r = 0.6 * np.sqrt(blob.area)
            same = [i for i, o in enumerate(blobs) if np.hypot(o.center[0] - blob.center[0], o.center[1] - blob.center[1]) < r]
            if not same:
                blobs.append(blob)
            elif all(blob.score > blobs[i].score for i in same):
                blobs = [o for i, o in enumerate(blobs) if i not in same] + [blob]
    blobs.sort(key=lambda b: -b.score)
    return blobs[:max_candidates]


def confirm_dots(photo: np.ndarray, expected_px: np.ndarray, areas_px2: np.ndarray,
                 tolerance_px: float) -> np.ndarray:
    """Centres of the dot markers found where they are expected, measured there alone (no search).

    A dot of known area is refined (the coverage centroid :func:`detect_dots` uses) in a box of
    its radius plus ``tolerance_px`` around its expected centre; it is *confirmed* when the
    centroid lies within ``tolerance_px`` of that centre and the measured area is within a factor 2
    of ``areas_px2``. A few boxes instead of the whole frame: the cheap check of a camera that did
    not move (:class:`~layerwatch.monitor.marker_watch.MarkerWatch`).

    Parameters
    ----------
    photo : ndarray, shape (h, w) or (h, w, 3)
        BGR or grey camera frame (a grey one is used as it is).
    expected_px : ndarray, shape (M, 2)
        Expected centres (u, v), px.
    areas_px2 : ndarray, shape (M,)
        Each dot's area as last detected (:attr:`Blob.area`), px^2; non-finite: not checked.
    tolerance_px : float
        Largest distance of a confirmed centre from its expected place, px.

    Returns
    -------
    ndarray, shape (M, 2), float64
        The confirmed centres; NaN rows for dots not confirmed.
    """
    grey = to_grey(photo)
    expected = np.asarray(expected_px, np.float64).reshape(-1, 2)
    areas = np.asarray(areas_px2, np.float64).reshape(-1)
    out = np.full_like(expected, np.nan)
    for i, ((u, v), area) in enumerate(zip(expected, areas, strict=True)):
        if not (np.isfinite(area) and area > 0 and 0 <= u < grey.shape[1] and 0 <= v < grey.shape[0]):
            continue
        half = np.sqrt(area / np.pi) + tolerance_px
        side = int(np.ceil(2 * half))
        ref = _refine(grey, (int(round(u - half)), int(round(v - half)), side, side))
        if ref is not None and np.hypot(ref[0] - u, ref[1] - v) <= tolerance_px and 0.5 <= ref[2] / area <= 2.0:
            out[i] = ref[:2]
    return out


def _aruco_dictionary(name: str):
    const = getattr(cv2.aruco, name, None)
    if not isinstance(const, int):
        raise MarkerError(f"unknown ArUco dictionary {name!r}; use e.g. DICT_4X4_50 or DICT_APRILTAG_36h11.")
    return cv2.aruco.getPredefinedDictionary(const)


def detect_aruco(photo: np.ndarray, dictionary: str = "DICT_4X4_50") -> dict[int, np.ndarray]:
    """Detect ArUco/AprilTag markers: ``{id: centre (2,) float64 px}``.

    The centre is the intersection of the tag's diagonals. Raises
    :class:`MarkerError` when an id is seen twice.
    """
    grey = to_grey(photo)
    det = cv2.aruco.ArucoDetector(_aruco_dictionary(dictionary), cv2.aruco.DetectorParameters())
    corners, ids, _ = det.detectMarkers(grey)
    out: dict[int, np.ndarray] = {}
    if ids is None:
        return out
    for quad, i in zip(corners, ids.reshape(-1), strict=True):
        p = quad.reshape(4, 2).astype(np.float64)
        a, b, c, d = p
        # intersection of lines a-c and b-d
        l1, l2 = np.cross([*a, 1], [*c, 1]), np.cross([*b, 1], [*d, 1])
        q = np.cross(l1, l2)
        centre = q[:2] / q[2] if abs(q[2]) > 1e-12 else p.mean(0)
        if int(i) in out:
            raise MarkerError(f"ArUco id {int(i)} appears twice in the photo; remove the duplicate tag.")
        out[int(i)] = centre
    return out
