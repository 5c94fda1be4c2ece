"""numpy's linear percentile, step by step, for code that selects its own order statistics.

:func:`numpy.percentile` (``method="linear"``) sorts or partitions once per call. A caller that
already partitions its values for other statistics (a median beside a percentile, a small box's
background and peak) only needs the two order statistics a percentile reads and numpy's arithmetic
on them; :func:`linear_index` and :func:`lerp` are that arithmetic, so the figures are numpy's bit for
bit (tested by the callers against :func:`numpy.percentile`). :func:`ranked_u8` selects the order
statistics of 8-bit values from their counts, without partitioning them.
"""

from __future__ import annotations

import numpy as np


def linear_index(n: int, q: float) -> tuple[int, int, float]:
    """The order statistics ``(lo, hi)`` the ``q``-th percentile of ``n`` values reads, and its weight.

    Parameters
    ----------
    n : int
        Number of values (>= 1).
    q : float
        Percentile in [0, 100] (a Python float, as numpy receives it).

    Returns
    -------
    lo, hi : int
        Ranks (0-based, ascending) of the two values interpolated; both ``n - 1`` at the top.
    t : float
        numpy's weight: the virtual index ``(n - 1) q / 100`` (float64) less its floor, or less
        ``n - 1`` at the top.
    """
    virtual = (n - 1) * np.true_divide(q, 100)
    lo = int(np.floor(virtual))
    if virtual >= n - 1:
        return n - 1, n - 1, float(virtual - (n - 1))
    return lo, lo + 1, float(virtual - np.floor(virtual))


def lerp(a, b, t: float) -> float:
    """numpy's ``_lerp`` of the two order statistics ``a <= b`` with weight ``t`` (in their dtype)."""
    diff = b - a
    return float(b - diff * (1 - t) if t >= 0.5 else a + diff * t)


def ranked_u8(values: np.ndarray, ranks: list[int]) -> np.ndarray:
    """The values at sorted positions ``ranks`` (0-based, ascending) of a uint8 array, read from its 256 counts.

    ``np.partition(values.ravel(), ranks)[ranks]``, value for value (integers: no order to break ties in),
    as int64, for one counting pass instead of a partition.

    Raises
    ------
    ValueError
        ``values`` is not uint8, or a rank is not in ``0..values.size - 1``.
    """
    if values.dtype != np.uint8:
        raise ValueError(f"expected uint8 values, got {values.dtype}")
    r = np.asarray(ranks, np.int64)
    if r.size and (r.min() < 0 or r.max() >= values.size):
        raise ValueError(f"ranks {ranks} outside 0..{values.size - 1}")
    cum = np.cumsum(np.bincount(values.ravel(), minlength=256))
    return np.searchsorted(cum, r, side="right")
