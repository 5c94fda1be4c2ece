"""The camera-fault gate: is a frame fit for analysis at all?

A black, over-exposed, flat, pure-noise, badly blurred or JPEG-blocked frame,
a frame that repeats the previous one (a lagged or frozen stream, with or
without fresh sensor noise), or a frame in which the bed markers sit away
from where they were, is a *camera* fault: comparing it with the layer's
reference would report "material outside the part" and pause a good print.
:func:`assess_frame` says which of these a frame shows; the monitor records a
failing frame with its reasons, alerts after a few in a row and never lets it
count toward a pause.

The checks are made so that a real print failure passes: spaghetti, a
foreign body or a shifted part change the *scene*, not the camera, so they
leave exposure, noise, sharpness and blocking alone and differ from the
previous frame by structure, not noise. Markers hidden by spaghetti are not
a fault; only visible markers away from their place are.

Two camera faults need the job, not the frame alone, and are the monitor's
(:mod:`layerwatch.monitor.camera_checks`): it detects the calibration's bed
markers in each frame and passes them here (``markers_px``,
``expected_markers_px``); and a stream that stays one layer late for good (each
frame a new picture, of the layer before) is told by analysing a frame that
would count toward a pause against the previous layer's reference.

All functions are pure: arrays in, figures out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from pydantic import Field

from layerwatch.analysis.area_reduce import area_resize
from layerwatch.analysis.histogram import middle_values, percentiles
from layerwatch.percentile import lerp, linear_index, median, order_statistics
from layerwatch.settings_base import Section

__all__ = ["FrameQuality", "FrameQualitySettings", "assess_frame", "compact_previous", "grey_of", "noise_sigma", "blockiness",
           "sharpness", "change_from", "gain_fit", "marker_offset_px", "marker_search_px", "marker_shift_px",
           "REPEATED_FRAME"]

#: width of the reduced grey image the exposure, sharpness and change checks use, px
WORK_WIDTH = 640
#: how the reason of a frame refused as a repeat of the previous one begins (the monitor's alert reads it)
REPEATED_FRAME = "same picture as the previous frame"

#: The 3x3 kernel of Immerkaer's noise estimate (Immerkaer 1996, "Fast noise variance estimation"):
#: it cancels planes and most edges; its response to white noise of std s has std 6 s.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
#: its separable factor (``_NOISE_KERNEL`` is its outer product with itself): two 3-tap passes instead of 9 taps
_NOISE_ROW = np.array([1, -2, 1], np.float32)


class FrameQualitySettings(Section):
    """Limits of the camera-fault gate (config section ``[frame_quality]``).

    Grey levels are of an 8-bit image (0-255); the defaults pass the real photos in the
    project's data set (exposure drift, glare, glass beds, dark filament) and the simulator's
    clean and failed layers (see ``benchmarks/frame_quality_gate.py``).

    Attributes
    ----------
    enabled : bool
        Run the gate at all.
    dark_p99 : float
        A frame whose 99th grey percentile is below this is black (light off, lens covered).
    bright_fraction : float
        A frame with more than this fraction of pixels >= 250 is over-exposed.
    min_range : float
        Least spread between the 1st and 99th grey percentile (a flat, grey frame has less).
    max_noise : float
        Largest sensor-noise std (Immerkaer estimate, grey levels); a pure-noise frame has ~40-75.
    min_sharpness : float
        Least Laplacian std of the 640-px grey image, relative to its 1-99 % range
        (x 100); a defocused or smeared frame has less.
    max_blockiness : float
        Largest ratio of grey steps on the 8-px JPEG grid to steps elsewhere: ~1 for a normal
        JPEG, up to 2.1 for the heavily compressed real webcam photos of the data set, 2.7 for
        quality 15 and 3.7 for quality 5 (simulated 720p frames).
    min_change, max_repeat_spread : float
        A frame is a repeat of the previous accepted one (a lagged or frozen stream, with fresh
        noise or not) when its structured change from it is below ``min_change`` grey levels
        *and* the residual's spread is below ``max_repeat_spread`` (only sensor noise differs;
        a new exposure of an unchanged scene differs in light, see :func:`change_from`).
    max_marker_shift_px : float
        Largest shift of a visible bed marker from its expected place, px (at the frame's size).
    roi : bool
        With a calibrated camera (a bed pose), sensor noise, JPEG blocking and the change from the
        previous frame are measured on the photo box that the observed square on the bed and the
        print's prism (its reach, from the bed to its top) cover, with the bed markers
        (:func:`~layerwatch.geometry.roi.bed_roi`): what the analysis looks at, not the room around the
        printer (a person walking by behind it no longer hides a repeated frame); about half of the
        frame and a third of the gate's cost with the simulator's camera. Exposure and sharpness stay
        the whole frame's. Off: the whole frame for every figure.
    excuse_late_frames : bool
        A frame that shows the previous layer is judged against that layer, so a camera one
        layer late does not pause a clean print. The monitor tells a late camera from a layer
        that added nothing (a clog, a part torn off into spaghetti) over the series, not from
        one photo (:class:`~layerwatch.monitor.camera_checks.LateStream`: progress since the
        previous frame where the G-code printed, and a repeated or unusable frame before the
        stretch). Off: such a frame is alerted and judged as it is.
    """

    enabled: bool = True
    dark_p99: float = Field(30.0, ge=0, le=255)
    bright_fraction: float = Field(0.5, gt=0, le=1)
    min_range: float = Field(20.0, ge=0, le=255)
    max_noise: float = Field(20.0, gt=0, le=255)
    min_sharpness: float = Field(1.0, ge=0, le=100)
    max_blockiness: float = Field(2.4, gt=1, le=100)
    min_change: float = Field(2.0, ge=0, le=255)
    max_repeat_spread: float = Field(1.5, ge=0, le=255)
    max_marker_shift_px: float = Field(12.0, gt=0, le=10_000)
    roi: bool = True
    excuse_late_frames: bool = True


@dataclass(frozen=True)
class FrameQuality:
    """Verdict of :func:`assess_frame`.

    Attributes
    ----------
    ok : bool
        The frame may be analysed.
    reasons : list of str
        One short reason per failed check (empty when ``ok``), e.g.
        ``"black frame (99th percentile 12/255)"``.
    figures : dict of str to float
        Every measured figure (``p1``, ``p99``, ``bright``, ``noise``, ``sharpness``,
        ``blockiness``, ``change``, ``change_spread``, ``marker_shift_px``), for records and tuning.
    """

    ok: bool
    reasons: list[str] = field(default_factory=list)
    figures: dict[str, float] = field(default_factory=dict)


def grey_of(image: np.ndarray) -> np.ndarray:
    """8-bit grey image of a BGR or grey ``uint8`` array, shape (H, W).

    Raises
    ------
    ValueError
        Not a 2-D or (H, W, 3|4) ``uint8`` array.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or img.ndim == 3 and img.shape[2] not in (1, 3, 4):
        raise ValueError(f"expected a uint8 (H, W) or (H, W, 3) image, got {img.dtype} {img.shape}")
    if img.ndim == 2:
        return img
    return img[..., 0] if img.shape[2] == 1 else cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_BGR2GRAY)


def _shrunk(grey: np.ndarray, width: int = WORK_WIDTH) -> np.ndarray:
    """``grey`` area-averaged to ``width`` px wide (not enlarged), uint8 as given."""
    h, w = grey.shape
    if w > width:
        grey = area_resize(grey, (width, max(1, round(h * width / w))))
    return grey


def _reduced(grey: np.ndarray, width: int = WORK_WIDTH) -> np.ndarray:
    """``grey`` area-averaged to ``width`` px wide (not enlarged), float32."""
    return _shrunk(grey, width).astype(np.float32)


def _given_small(small: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A caller's reduced grey frame as :func:`_reduced` makes it (float32), checked for its size."""
    h, w = shape[:2]
    want = (max(1, round(h * WORK_WIDTH / w)), WORK_WIDTH) if w > WORK_WIDTH else (h, w)
    if np.shape(small) != want:
        raise ValueError(f"small has shape {np.shape(small)}, not {want}: pass compact_previous(frame)")
    return np.asarray(small, np.float32)


def _reduced_box(box: tuple[slice, slice], shape: tuple[int, ...], small_shape: tuple[int, ...]) -> tuple[slice, slice]:
    """``box`` (rows, columns of a frame of ``shape``) in the frame reduced to ``small_shape``: each bound scaled and
    rounded (the reduced pixels of the box exactly when the reduction factor is a whole number dividing its bounds,
    as :data:`~layerwatch.geometry.roi.ROI_ALIGN` makes them at the common frame sizes)."""
    out = []
    for sl, n, m in zip(box, shape[:2], small_shape[:2], strict=True):
        start, stop, _ = sl.indices(n)
        out.append(slice(round(start * m / n), max(round(stop * m / n), round(start * m / n) + 1)))
    return out[0], out[1]


def compact_previous(image_bgr: np.ndarray) -> np.ndarray:
    """What :func:`assess_frame` needs of a frame passed later as ``previous``: its grey at ``WORK_WIDTH``.

    uint8 (h, w), 640 px wide: about 20x smaller than a 1080p BGR frame, and judged
    exactly as the frame itself (``assess_frame`` reduces ``previous`` the same way).
    """
    return _shrunk(grey_of(image_bgr))


def noise_sigma(grey: np.ndarray) -> float:
    """Sensor-noise std of a grey image, grey levels (Immerkaer's estimate, median form).

    The median of ``|I * N|`` over the image, / 0.6745 / 6, is the std of white noise and
    ignores edges and texture that cover less than half the image (a spaghetti nest).
    For a uint8 image the response is an integer (at most 16 x 255), so its median is read
    from the histogram of ``|I * N|`` (the same value as sorting, a few ms at 1080p).
    """
    g = np.asarray(grey)
    if g.dtype != np.uint8:
        resp = cv2.filter2D(g.astype(np.float32), -1, _NOISE_KERNEL)[1:-1, 1:-1]
        return float(np.median(np.abs(resp)) / 0.6745 / 6.0)
    # exact: integer taps, every partial sum an integer, |response| <= 2040 (two separable passes, 0.6 ms at 1080p
    # against 1.3 for the 3 x 3 kernel; the same int16 response, tested)
    resp = cv2.sepFilter2D(g, cv2.CV_16S, _NOISE_ROW, _NOISE_ROW)[1:-1, 1:-1]
    if resp.size == 0:
        return float("nan")
    # |response| saturated to 255 keeps the order of every smaller value: its 256-bin histogram (one
    # OpenCV pass) gives the median exactly unless the median itself reaches 255 (a pure-noise frame)
    low = cv2.calcHist([cv2.convertScaleAbs(resp)], [0], None, [256], [0, 256]).ravel().astype(np.int64)
    lo, hi = middle_values(low)
    if hi >= 255:
        lo, hi = middle_values(np.bincount(np.abs(resp).ravel()))
    return float(np.float32((lo + hi) / 2.0) / 0.6745 / 6.0)


def blockiness(grey: np.ndarray, block: int = 8) -> float:
    """Ratio of mean grey steps across the JPEG block grid to steps inside blocks (1 = no blocking).

    The steps ``|I(x+1) - I(x)|`` are summed per column (rows for the vertical steps), then per
    offset within the block; exactly, in integers, for a uint8 image.
    """
    g = np.asarray(grey)
    exact = g.dtype == np.uint8
    g = g if exact else g.astype(np.float32)
    ratios = []
    for steps, axis in ((cv2.absdiff(g[:, 1:], g[:, :-1]), 0), (cv2.absdiff(g[1:], g[:-1]), 1)):
        length = steps.shape[1 - axis]  # steps along the direction judged
        n = length // block * block
        if n < 2 * block:
            return 1.0
        sums = cv2.reduce(steps, axis, cv2.REDUCE_SUM, dtype=cv2.CV_32S if exact else cv2.CV_64F).ravel()[:n]
        per = sums.astype(np.float64 if not exact else np.int64).reshape(-1, block).sum(axis=0) / (
            steps.shape[axis] * (n // block))
        inside = np.delete(per, block - 1).mean()
        ratios.append(float((per[block - 1] + 0.5) / (inside + 0.5)))
    return float(np.mean(ratios))


def sharpness(small: np.ndarray, spread: float) -> float:
    """Laplacian std of a reduced grey image per 100 grey levels of its 1-99 % spread."""
    return float(cv2.Laplacian(small, cv2.CV_32F).std() * 100.0 / max(spread, 1.0))


def change_from(small: np.ndarray, previous: np.ndarray) -> tuple[float, float]:
    """Structured change of a reduced grey frame from the previous one, and the residual's spread.

    The previous frame is first matched in gain and offset (auto-exposure drift is no
    change); the residual is smoothed over 5 x 5 px (sensor noise averages out, a new
    layer or a failure does not).

    Returns
    -------
    change : float
        99.9th percentile of the residual's deviation less 3 robust stds, grey levels: ~0
        for a repeated frame even with fresh noise, several grey levels for a new layer.
    spread : float
        Robust std of the smoothed residual, grey levels: below ~1 when only sensor noise
        differs, more when the light or the scene changed.
    """
    if previous.shape != small.shape:
        return float("inf"), float("inf")
    a, b = gain_fit(previous.ravel()[::7], small.ravel()[::7])
    resid = cv2.blur(small - (a * previous + b), (5, 5))
    # order statistics selected, not the whole residual partitioned (percentile.order_statistics: the same values,
    # so the same figures bit for bit; a zero median's sign may differ, which the absolute value takes away)
    dev = np.abs(resid - float(median(resid.ravel())))
    med, tail = _median_and_percentile(dev.ravel(), 99.9)
    spread = float(med / 0.6745)
    return float(max(tail - 3.0 * spread, 0.0)), spread


def gain_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares line ``y ~ a x + b`` of two (n,) arrays: ``numpy.polyfit(x, y, 1)`` in closed form.

    The centred sums in float64 (grey levels of a few ten thousand pixels: exact to ~1e-12 of the
    fit; polyfit's scaled least squares differs from it by rounding only, ~1e-13, tested), ~0.2 ms
    instead of ~1.5 for polyfit's general solver. A constant ``x`` (no line) is left to polyfit.
    """
    xd, yd = np.asarray(x, np.float64), np.asarray(y, np.float64)
    mx, my = float(xd.mean()), float(yd.mean())
    dx = xd - mx
    sxx = float(np.dot(dx, dx))
    if not sxx > 0:
        a, b = np.polyfit(xd, yd, 1)
        return np.float64(a), np.float64(b)
    a = np.float64(float(np.dot(dx, yd - my)) / sxx)
    return a, np.float64(my - a * mx)  # NumPy floats, as polyfit's: ``a * image`` stays float64


def _median_and_percentile(values: np.ndarray, q: float) -> tuple[float, float]:
    """``numpy.median(values)`` and ``numpy.percentile(values, q)`` (linear) of a float64 (n,) array, bit for bit,
    from the order statistics both need, selected together (:func:`~layerwatch.percentile.order_statistics`;
    numpy partitions once per statistic).

    numpy's arithmetic on them is followed step for step: the mean of the middle one or two for the median, the
    virtual index ``(n - 1) q / 100``, its floor, and ``_lerp`` with a Python-float weight (``q`` is a Python float)
    for the percentile. ``values`` is not changed.
    """
    n = values.size
    mid = [n // 2 - 1, n // 2] if n % 2 == 0 else [(n - 1) // 2]
    lo, hi, t = linear_index(n, q)
    ks = sorted({*mid, lo, hi})
    got = dict(zip(ks, order_statistics(values, ks)[0], strict=True))
    med = float(np.mean(np.array([got[k] for k in mid], values.dtype)))
    return med, lerp(got[lo], got[hi], t)


def marker_search_px(shape: tuple[int, ...]) -> float:
    """How far from its expected place (px) a marker detected in a frame of ``shape`` = (h, w, ...) is taken for it:
    8 % of the frame's diagonal."""
    return 0.08 * float(np.hypot(shape[0], shape[1]))


def _marker_displacements(found_px: np.ndarray, expected_px: np.ndarray, search_px: float) -> np.ndarray:
    """``found - expected`` of each expected marker whose nearest detection lies within ``search_px``, shape (n, 2) px."""
    found = np.asarray(found_px, np.float64).reshape(-1, 2)
    expected = np.asarray(expected_px, np.float64).reshape(-1, 2)
    if len(found) == 0 or len(expected) == 0:
        return np.zeros((0, 2))
    diff = found[None, :, :] - expected[:, None, :]
    d = np.linalg.norm(diff, axis=2)
    nearest = d.argmin(axis=1)
    rows = np.arange(len(expected))
    return diff[rows, nearest][d[rows, nearest] <= search_px]


def marker_shift_px(found_px: np.ndarray, expected_px: np.ndarray, search_px: float) -> float | None:
    """Median distance of the markers seen to their expected places, px; None when fewer than 2 are seen.

    Parameters
    ----------
    found_px : ndarray, shape (K, 2)
        Detected marker centres (a spaghetti strand or a clip may add false ones).
    expected_px : ndarray, shape (M, 2)
        Where the markers were (the calibration's projection), same image size.
    search_px : float
        Only markers within this distance of an expected place count as seen.
    """
    seen = np.linalg.norm(_marker_displacements(found_px, expected_px, search_px), axis=1)
    return float(np.median(seen)) if len(seen) >= 2 else None


def marker_offset_px(found_px: np.ndarray, expected_px: np.ndarray, search_px: float) -> tuple[float, float] | None:
    """How far the camera's image moved, from the bed markers: the median ``(du, dv)`` of the markers seen, px.

    The markers lie on the bed, which does not move: a common offset of theirs is the camera's (a bumped or
    sagging mount), whatever the part did. Arguments as :func:`marker_shift_px`; None when fewer than 2 are seen.
    """
    d = _marker_displacements(found_px, expected_px, search_px)
    if len(d) < 2:
        return None
    du, dv = np.median(d, axis=0)
    return float(du), float(dv)


def _exposure_reasons(small: np.ndarray, s: FrameQualitySettings, fig: dict[str, float],
                      small_u8: np.ndarray | None = None) -> list[str]:
    """Black, over-exposed or flat frame; ``small_u8``: the reduced grey frame as uint8 (``small`` is its float32),
    whose 256-bin histogram gives the same percentiles and white share, bit for bit, without partitioning it."""
    if small_u8 is not None:
        counts = cv2.calcHist([small_u8], [0], None, [256], [0, 256]).ravel().astype(np.int64)
        p1, p99 = percentiles(counts, (1, 99))
        bright = int(counts[250:].sum()) / int(counts.sum())
    else:
        p1, p99 = (float(v) for v in np.percentile(small, (1, 99)))
        bright = float(np.mean(small >= 250))
    fig.update(p1=p1, p99=p99, bright=bright)
    out = []
    if p99 < s.dark_p99:
        out.append(f"black frame (99th percentile {p99:.0f}/255): light off or lens covered")
    if fig["bright"] > s.bright_fraction:
        out.append(f"over-exposed ({fig['bright']:.0%} of pixels white): lower the exposure or the light")
    if p99 - p1 < s.min_range and not out:
        out.append(f"no dynamic range (grey {p1:.0f}-{p99:.0f}): the picture is flat")
    return out


def assess_frame(image_bgr: np.ndarray, previous: np.ndarray | Sequence[np.ndarray] | None = None,
                 settings: FrameQualitySettings | None = None, *, markers_px: np.ndarray | None = None,
                 expected_markers_px: np.ndarray | None = None, small: np.ndarray | None = None,
                 box: tuple[slice, slice] | None = None) -> FrameQuality:
    """Check one camera frame before analysis.

    Parameters
    ----------
    image_bgr : ndarray, uint8, shape (H, W, 3) or (H, W)
        The frame.
    previous : ndarray or sequence of ndarray, optional
        The last frame(s) that passed, oldest first, same camera; a frame that differs from
        the last of them by noise only is a repeated (lagged or frozen) frame.
    settings : FrameQualitySettings, optional
        Limits (defaults when omitted).
    markers_px : ndarray, shape (K, 2), optional
        Bed-marker centres detected in this frame (see :mod:`layerwatch.geometry.markers`).
    expected_markers_px : ndarray, shape (M, 2), optional
        Where the markers are expected (the calibration's projection at this frame's size).
    small : ndarray, uint8, shape (h, WORK_WIDTH), optional
        :func:`compact_previous` of this frame when the caller has it (it keeps it as the next
        frame's ``previous``): not reduced again.
    box : (slice, slice), optional
        Region of interest (rows, columns of the frame; :func:`~layerwatch.geometry.roi.bed_roi`: where
        the bed and the print are): sensor noise, JPEG blocking and the change from ``previous`` are
        measured there alone (the change on the box's part of the reduced frames); exposure and
        sharpness are the whole frame's, as without a box. Start it on the 8-px JPEG grid.

    Returns
    -------
    FrameQuality
        ``ok`` is False when any check fails; ``figures`` holds every measured value.

    Raises
    ------
    ValueError
        ``image_bgr`` is not an 8-bit image (the caller's camera check comes first).
    """
    s = settings or FrameQualitySettings()
    grey = grey_of(image_bgr)
    if small is None:
        small_u8: np.ndarray | None = _shrunk(grey)
        small = np.asarray(small_u8).astype(np.float32)  # (_reduced)
    else:
        small_u8 = np.ascontiguousarray(small) if np.asarray(small).dtype == np.uint8 else None
        small = _given_small(small, grey.shape)
    fig: dict[str, float] = {}
    reasons = _exposure_reasons(small, s, fig, small_u8)
    roi = grey if box is None else grey[box]
    if roi.size == 0:
        raise ValueError(f"the box {box} holds no pixel of the {grey.shape[1]}x{grey.shape[0]} frame")
    fig["noise"] = noise_sigma(roi)
    fig["blockiness"] = blockiness(roi)
    fig["sharpness"] = sharpness(small, fig["p99"] - fig["p1"])
    if not reasons:  # a black or white frame has no noise, blocks or edges worth judging
        if fig["noise"] > s.max_noise:
            reasons.append(f"noise (std {fig['noise']:.0f} grey levels): the picture is mostly sensor noise")
        elif fig["sharpness"] < s.min_sharpness:
            reasons.append(f"blurred (sharpness {fig['sharpness']:.2f}): refocus or clean the lens")
        if fig["blockiness"] > s.max_blockiness:
            reasons.append(f"JPEG blocking ({fig['blockiness']:.1f}x): raise the camera's JPEG quality")
    prev = previous[-1] if isinstance(previous, Sequence) and len(previous) else previous
    if isinstance(prev, np.ndarray) and not reasons:
        before = _reduced(grey_of(prev))
        if box is not None and before.shape == small.shape:  # the box's part of both reduced frames
            cut = _reduced_box(box, grey.shape, small.shape)
            fig["change"], fig["change_spread"] = change_from(small[cut], before[cut])
        else:
            fig["change"], fig["change_spread"] = change_from(small, before)
        if fig["change"] < s.min_change and fig["change_spread"] < s.max_repeat_spread:
            reasons.append(f"{REPEATED_FRAME} (change {fig['change']:.1f} grey levels): "
                           "the stream is lagging or frozen")
    if markers_px is not None and expected_markers_px is not None:
        shift = marker_shift_px(markers_px, expected_markers_px, marker_search_px(grey.shape))
        if shift is not None:
            fig["marker_shift_px"] = shift
            if shift > s.max_marker_shift_px:
                reasons.append(f"bed markers {shift:.0f} px from their place: the camera moved; recalibrate")
    return FrameQuality(not reasons, reasons, fig)
