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
from numba import njit


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


#: below this many values :func:`order_statistics` partitions them all (bracketing would not pay)
BRACKET_MIN = 16384
#: the sample that brackets the wanted ranks: every ``BRACKET_STEP``-th value
BRACKET_STEP = 16


@njit(cache=True, nogil=True)
def _bracket_pass(values, lo, hi, inside):  # pragma: no cover - jit
    """One pass over ``values`` (n,): how many are ``< lo``, how many lie in ``[lo, hi]`` (copied in order into
    ``inside``, as many as fit) and how many are NaN. Branch-free, the counts in registers."""
    cap = inside.size
    below = 0
    count = 0
    nans = 0
    for i in range(values.size):
        v = values[i]
        nans += v != v
        below += v < lo
        inside[min(count, cap - 1)] = v
        count += (v >= lo) & (v <= hi)
    return below, count, nans


def _brackets(n: int, m: int, ranks: list[int]) -> list[tuple[int, int, list[int]]]:
    """Sample ranks ``(a, b)`` bracketing each wanted rank of ``n`` values in a sample of ``m``, overlapping ones
    merged, with the ranks each holds."""
    d = 4 * int(np.sqrt(m)) + 16
    out: list[tuple[int, int, list[int]]] = []
    for k in sorted(set(ranks)):
        s = k * m // n
        a, b = max(s - d, 0), min(s + d, m - 1)
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], b, out[-1][2] + [k])
        else:
            out.append((a, b, [k]))
    return out


def order_statistics(values: np.ndarray, ranks: list[int]) -> tuple[np.ndarray, bool]:
    """The values at sorted positions ``ranks`` of a flat float array, and whether it holds a NaN.

    ``np.partition(values, ranks)[ranks]`` value for value (NaNs sort last; only the sign of a zero may
    differ: the two orders compare equal), without partitioning every value: a strided sample brackets each
    rank between two of its values, one pass (:func:`_bracket_pass`) counts the values below each bracket
    and copies those inside, and only those are partitioned. When a rank does not fall inside its bracket
    (a sample unlike the values) the values are partitioned as a whole, so the result is exact either way.
    ``values`` is not changed.

    Parameters
    ----------
    values : ndarray, float32 or float64, shape (n,)
        At least one value.
    ranks : list of int
        0-based ascending positions, each in ``0..n - 1``.

    Returns
    -------
    stats : ndarray, shape (len(ranks),), the dtype of ``values``
    has_nan : bool
    """
    v = np.asarray(values)
    if v.ndim != 1 or v.dtype not in (np.float32, np.float64) or v.size == 0:
        raise ValueError(f"expected a non-empty flat float32/float64 array, got {v.dtype} {v.shape}")
    n = v.size
    if any(not 0 <= k < n for k in ranks):
        raise ValueError(f"ranks {ranks} outside 0..{n - 1}")
    if n < BRACKET_MIN:
        return np.partition(v, ranks)[ranks], bool(np.isnan(v).any())
    sample = v[::BRACKET_STEP].copy()
    m = sample.size
    groups = _brackets(n, m, ranks)
    sample.partition(sorted({r for a, b, _ in groups for r in (a, b)}))
    cap = max(2 * (max(b - a for a, b, _ in groups) + 1) * BRACKET_STEP, 256)
    inside = np.empty(cap, v.dtype)
    found: dict[int, np.floating] = {}
    has_nan = False
    for a, b, ks in groups:
        lo = sample[a] if a > 0 else v.dtype.type(-np.inf)
        hi = sample[b] if b < m - 1 else v.dtype.type(np.inf)
        below, count, nans = _bracket_pass(v, lo, hi, inside)
        has_nan = nans > 0
        local = [k - below for k in ks]
        if count > cap or local[0] < 0 or local[-1] >= count:
            return np.partition(v, ranks)[ranks], has_nan
        part = np.partition(inside[:count], local)
        found.update(zip(ks, part[local], strict=True))
    return np.array([found[k] for k in ranks], v.dtype), has_nan


def median(values: np.ndarray) -> np.floating:
    """:func:`numpy.median` of a flat float32/float64 array, bit for bit but for the sign of a zero median: the mean
    (numpy's) of its middle one or two values (:func:`order_statistics`), NaN when it holds one, as numpy's."""
    v = np.asarray(values)
    n = v.size
    ks = [n // 2 - 1, n // 2] if n % 2 == 0 else [(n - 1) // 2]
    mid, has_nan = order_statistics(v, ks)
    return v.dtype.type(np.nan) if has_nan else np.mean(mid)
