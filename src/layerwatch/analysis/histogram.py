"""Order statistics read from histograms: the median and percentiles of integer values from their counts alone."""

from __future__ import annotations

import numpy as np

__all__ = ["middle_values", "percentiles"]


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


def percentiles(counts: np.ndarray, q: tuple[float, ...], dtype: type = np.float32) -> tuple[float, ...]:
    """:func:`numpy.percentile` (``method="linear"``) of a sample of integers given by their counts, bit for bit.

    The sample is the integers ``0..K-1``, each ``counts[v]`` times, held as ``dtype`` (as numpy would
    read ``sample.astype(dtype)``); numpy's own steps are followed on the two order statistics each
    percentile needs (virtual index ``(n - 1) q / 100`` in float64, its floor and the next, the
    interpolation of :func:`numpy.lib._function_base_impl._lerp`), so the figures are the ones
    ``numpy.percentile(sample, q)`` gives, without partitioning the sample.

    Parameters
    ----------
    counts : ndarray, shape (K,)
        How often each value occurs (integers; at least one in all).
    q : tuple of float
        Percentiles in [0, 100] (a tuple, as the caller would pass to numpy).
    dtype : type
        The sample's floating dtype.

    Returns
    -------
    tuple of float
    """
    n = int(np.sum(counts))
    cum = np.cumsum(counts)
    virtual = (n - 1) * np.true_divide(q, 100)
    prev = np.floor(virtual)
    nxt = prev + 1
    top = virtual >= n - 1
    prev[top] = nxt[top] = n - 1
    prev[virtual < 0], nxt[virtual < 0] = 0, 0
    a = np.searchsorted(cum, prev.astype(np.intp), side="right").astype(dtype)
    b = np.searchsorted(cum, nxt.astype(np.intp), side="right").astype(dtype)
    gamma = np.asanyarray(virtual - prev, dtype=virtual.dtype)
    diff = b - a
    out = np.add(a, diff * gamma)
    np.subtract(b, diff * (1 - gamma), out=out, where=gamma >= 0.5, casting="unsafe", dtype=out.dtype)
    return tuple(float(v) for v in out)
