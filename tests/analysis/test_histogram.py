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
