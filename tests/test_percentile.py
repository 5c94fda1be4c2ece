"""Order statistics selected by bracketing (``layerwatch.percentile``) against numpy's partition and median."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch import percentile
from layerwatch.percentile import BRACKET_MIN, BRACKET_STEP, median, order_statistics


def _samples(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Smooth, heavy-tailed, tied, constant, sorted and stride-periodic values (the last two mislead a strided
    sample: its brackets miss and the whole array is partitioned)."""
    periodic = rng.normal(0, 1, n)
    periodic[::BRACKET_STEP] += 1e6  # every sampled value far above the rest
    return [rng.normal(0, 2, n), np.abs(rng.standard_cauchy(n)), rng.integers(0, 4, n).astype(np.float64),
            np.full(n, 3.25), np.sort(rng.normal(0, 1, n)), np.sort(rng.normal(0, 1, n))[::-1].copy(), periodic,
            rng.normal(0, 1, n).astype(np.float32)]


@pytest.mark.parametrize("n", [1, 2, 1000, BRACKET_MIN - 1, BRACKET_MIN, BRACKET_MIN + 7, 107520, 230401])
def test_order_statistics_are_the_partitions_values(n):
    rng = np.random.default_rng(n)
    for v in _samples(rng, n):
        before = v.copy()
        ranks = sorted({0, n // 2 - 1 if n > 1 else 0, n // 2, int(0.999 * (n - 1)), n - 1, int(rng.integers(n))})
        got, has_nan = order_statistics(v, ranks)
        assert got.dtype == v.dtype and not has_nan
        assert np.array_equal(got, np.partition(v, ranks)[ranks])
        assert np.array_equal(v, before)  # not partitioned in place
        assert median(v) == np.median(v) and median(v).dtype == np.median(v).dtype


def test_nans_sort_last_and_make_the_median_nan():
    rng = np.random.default_rng(4)
    for n in (101, 40001):
        v = rng.normal(0, 1, n)
        v[rng.integers(0, n, 30)] = np.nan
        low = [0, n // 3, n // 2]
        got, has_nan = order_statistics(v, low)
        assert has_nan and np.array_equal(got, np.partition(v, low)[low])
        assert np.isnan(median(v)) and np.isnan(np.median(v))
        top = [n - 1]  # a NaN rank: numpy's partition puts the NaNs there
        assert np.isnan(order_statistics(v, top)[0][0])


def test_repeated_ranks_and_bad_input():
    rng = np.random.default_rng(6)
    v = rng.normal(0, 1, 50000)
    got, _ = order_statistics(v, [10, 10, 25000, 25000])
    assert np.array_equal(got, np.sort(v)[[10, 10, 25000, 25000]])
    for bad in (np.zeros((4, 4)), np.zeros(0), np.zeros(5, np.int64)):
        with pytest.raises(ValueError):
            order_statistics(bad, [0])
    with pytest.raises(ValueError):
        order_statistics(v, [50000])


def test_a_smooth_sample_is_bracketed_not_partitioned_whole(monkeypatch):
    """On values like the gate's residuals each rank falls inside its bracket, which holds a small share of them
    (the speed-up: only those are partitioned)."""
    seen = []
    bracket = percentile._bracket_pass

    def spy(values, lo, hi, inside):
        out = bracket(values, lo, hi, inside)
        seen.append(out)
        return out

    monkeypatch.setattr(percentile, "_bracket_pass", spy)
    n = 107520
    v = np.random.default_rng(1).normal(0, 1, n)
    ranks = [n // 2 - 1, n // 2, int(0.999 * (n - 1))]
    assert np.array_equal(order_statistics(v, ranks)[0], np.partition(v, ranks)[ranks])
    assert len(seen) == 2  # the two middle ranks share one bracket
    for (below, count, nans), ks in zip(seen, (ranks[:2], ranks[2:]), strict=True):
        assert nans == 0 and all(below <= k < below + count for k in ks) and count < 0.15 * n
