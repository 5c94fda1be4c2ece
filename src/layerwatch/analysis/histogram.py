"""Order statistics read from histograms: the median of integer values from their counts alone."""

from __future__ import annotations

import numpy as np

__all__ = ["middle_values"]


def middle_values(counts: np.ndarray) -> tuple[int, int]:
    """The two middle values of a sample of integers given by their counts.

    Parameters
    ----------
    counts : ndarray, shape (K,)
        How often each value ``0..K-1`` occurs (integers, or floats holding integers; at least one).

    Returns
    -------
    (int, int)
        The values at sorted positions ``(n - 1) // 2`` and ``n // 2`` of the ``n`` values: the same
        one when ``n`` is odd; their mean is :func:`numpy.median` of the sample.
    """
    n = int(round(float(np.sum(counts))))
    cum = np.cumsum(counts)
    return int(np.searchsorted(cum, (n - 1) // 2, side="right")), int(np.searchsorted(cum, n // 2, side="right"))
