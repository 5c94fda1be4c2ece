"""The median read from counts is numpy's median of the sample."""

import numpy as np
import pytest

from layerwatch.analysis.histogram import middle_values


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 1001])
def test_middle_values_give_numpys_median(n):
    rng = np.random.default_rng(n)
    values = rng.integers(0, 40, n)
    lo, hi = middle_values(np.bincount(values, minlength=40).astype(np.float64))
    assert (lo + hi) / 2 == np.median(values)
    assert lo == np.sort(values)[(n - 1) // 2] and hi == np.sort(values)[n // 2]


@pytest.mark.parametrize("seed", range(6))
def test_percentiles_from_counts_are_numpys_bit_for_bit(seed):
    from layerwatch.analysis.histogram import percentiles

    rng = np.random.default_rng(seed)
    for n in (1, 2, 3, 100, 101, 230400, int(rng.integers(1, 100000))):
        for values in (rng.integers(0, 256, n), np.clip(rng.normal(rng.uniform(0, 255), 20, n), 0, 255).astype(int),
                       rng.choice(rng.integers(0, 256, 2), n), np.full(n, 7)):
            u8 = values.astype(np.uint8)
            counts = np.bincount(u8, minlength=256)
            for q in ((1, 99), (0, 100), (50,), (99.9,), (0.1, 33.3, 66.6)):
                want = tuple(float(v) for v in np.percentile(u8.astype(np.float32), q))
                assert percentiles(counts, q) == want, (n, q)
