"""scene_change._roi_scores: the one-pass path gives the block scores of the NumPy/OpenCV passes, bit for bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.analysis.scene_change import (
    SATURATED,
    _block_mean,
    _censored_absdiff,
    _roi_scores,
    _unclipped_pass,
    channel_max,
    channel_mean,
)


def _frozen_roi_scores(photo: np.ndarray, expected: np.ndarray, usable: np.ndarray, ratio: np.ndarray,
                       b: int, expected_clipped: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """_roi_scores as it was before the one-pass path (main 87e6fd2), frozen."""
    h, w = usable.shape
    n, m = h // b, w // b
    pred = expected * ratio
    np.minimum(pred, 255.0, out=pred)
    img = np.ascontiguousarray(photo)
    okf = usable.astype(np.float32)
    frac = cv2.resize(okf, (m, n), interpolation=cv2.INTER_AREA)
    in_photo = img >= SATURATED
    in_expected = expected >= SATURATED if expected_clipped is None else expected_clipped
    any_clip = channel_max(in_photo | in_expected) & usable
    okc = okf[..., None]
    clipped = None
    if any_clip.any():
        px = np.flatnonzero(any_clip)
        clipped = (px, in_expected.reshape(-1, 3)[px], in_photo.reshape(-1, 3)[px])
        okc = np.repeat(okc, 3, axis=2)
        okc.reshape(-1, 3)[px] = ~(clipped[1] | clipped[2])
    score = _block_mean(channel_mean(_censored_absdiff(img, pred, clipped)), okf, frac)
    sxy = cv2.resize(img * pred * okc, (m, n), interpolation=cv2.INTER_AREA)
    syy = cv2.resize(pred * pred * okc, (m, n), interpolation=cv2.INTER_AREA)
    gain = sxy / np.maximum(syy, 1e-6)
    if clipped is not None:
        fitted = syy > 1e-6
        other = (gain * fitted).sum(-1, keepdims=True) / np.maximum(fitted.sum(-1, keepdims=True), 1)
        gain = np.where(fitted, gain, np.where(fitted.any(-1, keepdims=True), other, 1.0)).astype(np.float32)
    g = cv2.resize(gain, (m * b, n * b), interpolation=cv2.INTER_NEAREST)
    shade_free = _block_mean(channel_mean(_censored_absdiff(img, g * pred, clipped)), okf, frac)
    return score, frac >= 0.5, shade_free


def _scene(shape: tuple[int, int], seed: int, clip: bool) -> tuple[np.ndarray, ...]:
    """A working-image crop (views of larger images, as change_blocks cuts them), its E, usable mask and ratio."""
    rng = np.random.default_rng(seed)
    h, w = shape
    big = cv2.GaussianBlur(rng.random((h + 20, w + 30, 3), dtype=np.float32) * 200 + 20, (0, 0), 1.2)
    photo = big[10:10 + h, 15:15 + w]
    expected = np.ascontiguousarray(photo * (0.9 + 0.2 * rng.random((h, w, 3), dtype=np.float32)))
    expected[rng.random((h, w)) < 0.05] += 30  # changed pixels
    ratio = (0.8 + 0.5 * rng.random((h, w, 3), dtype=np.float32))
    usable = rng.random((h, w)) > 0.2
    usable[: h // 3, : w // 4] = False  # whole blocks out
    if clip:
        photo[h // 2, w // 2, 0] = 252.0
        expected[3, 5] = 251.0
    return photo, expected, usable, ratio


@pytest.mark.parametrize("b", [8, 3, 5, 6, 16])
@pytest.mark.parametrize("clip", [False, True])
def test_block_scores_are_the_passes(b: int, clip: bool) -> None:
    photo, expected, usable, ratio = _scene((12 * b, 20 * b), b, clip)
    for ec in (None, expected >= SATURATED):
        got, want = _roi_scores(photo, expected, usable, ratio, b, ec), _frozen_roi_scores(
            photo, expected, usable, ratio, b, ec)
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype and np.array_equal(g, w)


def test_unusable_clipped_pixels_and_extremes() -> None:
    """Clipped channels on unusable pixels keep the one-pass path; predictions above 255 are clipped; zeros."""
    photo, expected, usable, ratio = _scene((96, 160), 3, False)
    photo[usable == 0] = 255.0
    expected[:8] *= 4.0  # ratio * E above 255
    photo[40:48, 40:48] = 0.0
    ratio[:, :16] = 0.0
    for ec in (None, np.zeros(expected.shape, bool)):
        for g, w in zip(_roi_scores(photo, expected, usable, ratio, 8, ec),
                        _frozen_roi_scores(photo, expected, usable, ratio, 8, ec), strict=True):
            assert np.array_equal(g, w)


def test_noisy_crops_take_the_one_pass_path() -> None:
    """Crops with sensor noise (and, every second one, a clipped channel): the one pass is taken where nothing
    usable is clipped, and the scores are the passes' either way."""
    rng = np.random.default_rng(21)
    for k in range(4):
        photo, expected, usable, ratio = _scene((240, 416), 40 + k, k % 2 == 1)
        photo = photo + rng.standard_normal(photo.shape).astype(np.float32)
        n, m = 240 // 8, 416 // 8
        pred, res = np.empty_like(photo), np.empty_like(photo)
        sums = np.empty((n, m, 3), np.float32), np.empty((n, m, 3), np.float32)
        clipped = _unclipped_pass(photo, expected, ratio, usable, expected >= SATURATED, 8, pred, res, *sums)
        assert clipped == (k % 2 == 1)
        for g, w in zip(_roi_scores(photo, expected, usable, ratio, 8, None),
                        _frozen_roi_scores(photo, expected, usable, ratio, 8, None), strict=True):
            assert np.array_equal(g, w)
