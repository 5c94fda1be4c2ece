"""analysis/block_moments: the five block means bit for bit as five cv2.resize(INTER_AREA) calls gave them."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.analysis.block_moments import block_moments
from layerwatch.analysis.extrusion import block_ncc
from layerwatch.analysis.layer_change import MIN_QUIET_BLOCKS, QUIET_MIN_VAR, pair_noise


def _five_resizes(a: np.ndarray, b: np.ndarray, bp: int, w: np.ndarray | None = None) -> list[np.ndarray]:
    """The replaced computation: NumPy's products, then one area resize each."""
    n, m = a.shape[0] // bp, a.shape[1] // bp
    crop = (slice(0, n * bp), slice(0, m * bp))
    x, y = np.ascontiguousarray(a[crop]), np.ascontiguousarray(b[crop])
    k = None if w is None else np.ascontiguousarray(w[crop])
    return [cv2.resize(v if k is None else v * k, (m, n), interpolation=cv2.INTER_AREA)
            for v in (x, y, x * x, y * y, x * y)]


def _frozen_block_ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray, block_px: int,
                      min_share: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """block_ncc as it was before block_moments (main 9c2fb92), frozen."""
    h, w = mask.shape
    n, m = h // block_px, w // block_px
    crop = (slice(0, n * block_px), slice(0, m * block_px))
    k = np.ascontiguousarray(mask[crop]).astype(np.float32)
    x, y = np.ascontiguousarray(a[crop]), np.ascontiguousarray(b[crop])

    def mean(v: np.ndarray) -> np.ndarray:
        return cv2.resize(v * k, (m, n), interpolation=cv2.INTER_AREA)

    frac = cv2.resize(k, (m, n), interpolation=cv2.INTER_AREA)
    f = np.maximum(frac, 1e-6)
    mx, my = mean(x) / f, mean(y) / f
    vx, vy = np.maximum(mean(x * x) / f - mx * mx, 0), np.maximum(mean(y * y) / f - my * my, 0)
    cov = mean(x * y) / f - mx * my
    ncc = np.where(vx * vy > 0, cov / np.sqrt(np.maximum(vx * vy, 1e-12)), 0.0).astype(np.float32)
    texture = np.sqrt(np.maximum(vx, vy))
    return np.clip(ncc, -1, 1), (frac >= min_share) & (texture > 0.5)


def _textures(shape: tuple[int, int], seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = (rng.standard_normal(shape) * 6).astype(np.float32)
    b = (0.7 * a + rng.standard_normal(shape) * 2).astype(np.float32)
    return a, b, rng.random(shape) > 0.35


@pytest.mark.parametrize("bp", [2, 3, 4, 5, 6, 7, 8, 12, 16])
@pytest.mark.parametrize("shape", [(408, 568), (35, 48), (101, 77)])
def test_five_means_are_opencvs(bp: int, shape: tuple[int, int]) -> None:
    a, b, mask = _textures(shape, bp + shape[1])
    weights = np.random.default_rng(bp).random(shape, dtype=np.float32) * 1.7  # any weight, not only a mask
    for w in (None, mask.astype(np.float32), weights):
        for got, want in zip(block_moments(a, b, bp, w), _five_resizes(a, b, bp, w), strict=True):
            assert got.dtype == np.float32 and got.shape == want.shape
            assert np.array_equal(got, want)


def test_ties_signs_and_views() -> None:
    """Repeated, negative and zero values; views with strides; a mask of zeros (products of -x and 0)."""
    rng = np.random.default_rng(4)
    a = np.round(rng.standard_normal((200, 264)) * 3).astype(np.float32)
    b = -a[::-1].copy()
    big = np.zeros((400, 600), np.float32)
    big[::2, :264] = a
    view = big[::2, :264]
    for w in (None, np.zeros(a.shape, np.float32), (a > 0).astype(np.float32)):
        for bp in (8, 16, 5):
            for got, want in zip(block_moments(view, b, bp, w), _five_resizes(a, b, bp, w), strict=True):
                assert np.array_equal(got, want)


def test_callers_are_unchanged() -> None:
    a, b, mask = _textures((408, 568), 1)
    for bp in (8, 6):
        got, want = block_ncc(a, b, mask, bp), _frozen_block_ncc(a, b, mask, bp)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    near = np.zeros(a.shape, bool)
    near[100:200, 150:300] = True
    noise = pair_noise(a, b, near, 16)
    va, vb = (np.maximum(s2 - s * s, 0) for s, s2 in zip(_five_resizes(a, b, 16)[:2], _five_resizes(a, b, 16)[2:4],
                                                          strict=True))
    ma, mb, _, _, mab = _five_resizes(a, b, 16)
    cov = mab - ma * mb
    n, m = va.shape
    calm = (cv2.resize(near[:n * 16, :m * 16].astype(np.float32), (m, n), interpolation=cv2.INTER_AREA) == 0) & (
        np.minimum(va, vb) > QUIET_MIN_VAR)
    assert calm.sum() >= MIN_QUIET_BLOCKS and noise == 0.5 * float(np.median((va + vb - 2 * cov)[calm]))


def test_refuses_mismatched_inputs() -> None:
    a = np.zeros((16, 16), np.float32)
    with pytest.raises(ValueError):
        block_moments(a, np.zeros((16, 8), np.float32), 4)
    with pytest.raises(ValueError):
        block_moments(a, a, 0)
    with pytest.raises(ValueError):
        block_moments(a, a, 4, np.zeros((8, 8), np.float32))
