"""The twelve block similarity measures of the paper's Table 2, vectorised.

Every measure compares two block tensors ``a`` and ``b`` of shape
``(..., k)`` block by block and returns a similarity in ``[0, 1]`` (float32,
never NaN) with 1 meaning identical.

Mappings (eq. 4, ``s = 1 - d / d_max``). HOG blocks are non-negative with
Euclidean norm <= 1 for every block normalisation (L2/L2-Hys: norm 1 or 0;
L1: sum <= 1; L1-sqrt: sum of squares <= 1). From these bounds:

==============  ==========================================  =============
name            d (or similarity)                           d_max
==============  ==========================================  =============
cosine          s = a.b / (|a| |b|)                          (d = 1 - s, 1)
sqeuclidean     |a - b|^2 <= |a|^2 + |b|^2 (as a.b >= 0)    2
euclidean       |a - b|                                     sqrt(2)
l1              sum |a_i - b_i| <= sqrt(k) |(a, b)|_2       sqrt(2 k)
hellinger       |sqrt(p) - sqrt(q)| / sqrt(2), p = a/sum a   1
sorensen        sum |a - b| / sum (a + b)  (Bray-Curtis)    1
clark           sqrt(sum ((a - b) / (a + b))^2), 0/0 := 0   sqrt(k)
jaccard         s = a.b / (|a|^2 + |b|^2 - a.b)  (Tanimoto)  (in [0, 1])
dice            s = 2 a.b / (|a|^2 + |b|^2)                  (in [0, 1])
pearson         s = (r + 1) / 2
spearman        s = (rho + 1) / 2, average ranks for ties
kendall         s = (tau_b + 1) / 2, tau-b with tie correction
==============  ==========================================  =============

Inputs outside those bounds (negative values, norms above 1) are allowed;
the result is clipped to ``[0, 1]``.

Note for L2 / L2-Hys blocks (unit norm): cosine, dice and sqeuclidean are
then the same number (``a.b``), and euclidean is ``1 - sqrt(1 - a.b)``; they
differ only for L1-type normalisations or empty blocks.

Corrections to Table 2: the Jaccard, Dice and Hellinger entries of the
paper's Table 2 are misprinted (project issue 7); we do not reproduce the
printed forms. We implement Jaccard and Dice in the inner-product
(Tanimoto / Dice) forms of Cha (2007), "inner product family", which
generalise the set measures to non-negative vectors, and the standard
Hellinger distance ``sqrt(1 - sum sqrt(p q))`` of the blocks normalised to
unit sum (Cha 2007, "fidelity family"; bounded by 1), computed in the
equivalent stable form ``|sqrt(p) - sqrt(q)| / sqrt(2)``.

Degenerate blocks (flat, featureless image areas give all-zero blocks):

* both blocks all-zero -> similarity 1 for every measure;
* one block all-zero: cosine, jaccard, dice, hellinger, sorensen -> 0
  (no shared structure); distance measures keep their finite value;
* Pearson/Spearman/Kendall are undefined for a constant vector
  (``max - min <= 1e-12``): both constant and equal -> 1, otherwise 0.

References
----------
Petsiuk & Pearce (2022), Table 2 and eq. (4);
S.-H. Cha (2007), "Comprehensive Survey on Distance/Similarity Measures
between Probability Density Functions", Int. J. Math. Models Methods Appl. Sci. 1(4).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from layerwatch.analysis.settings import METRIC_NAMES
from layerwatch.errors import AnalysisError

__all__ = ["similarity", "similarity_all", "METRIC_NAMES", "D_MAX", "average_ranks"]

_TINY = 1e-12

#: d_max of eq. (4) per distance measure as a function of k.
D_MAX = {
    "sqeuclidean": lambda k: 2.0,
    "euclidean": lambda k: math.sqrt(2.0),
    "l1": lambda k: math.sqrt(2.0 * k),
    "hellinger": lambda k: 1.0,
    "sorensen": lambda k: 1.0,
    "clark": lambda k: math.sqrt(k),
}


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...k,...k->...", a, b)


def _safe_div(num: np.ndarray, den: np.ndarray, both_zero: float) -> np.ndarray:
    out = np.full(np.broadcast(num, den).shape, both_zero, dtype=np.float64)
    np.divide(num, den, out=out, where=den > _TINY)
    return out


class _Pair:
    """Shared intermediate sums of one block pair (computed lazily once)."""

    def __init__(self, a: np.ndarray, b: np.ndarray) -> None:
        self.a, self.b, self.k = a, b, a.shape[-1]
        self._c: dict[str, np.ndarray] = {}

    def get(self, name: str) -> np.ndarray:
        if name not in self._c:
            self._c[name] = getattr(self, "_" + name)()
        return self._c[name]

    def _aa(self):
        return _dot(self.a, self.a)

    def _bb(self):
        return _dot(self.b, self.b)

    def _ab(self):
        return _dot(self.a, self.b)

    def _absdiff(self):
        return np.abs(self.a - self.b).sum(axis=-1)

    def _empty_a(self):  # all-zero block: Euclidean norm <= 1e-12
        return self.get("aa") <= _TINY * _TINY

    def _empty_b(self):
        return self.get("bb") <= _TINY * _TINY

    def _const_a(self):
        return np.ptp(self.a, axis=-1) <= _TINY

    def _const_b(self):
        return np.ptp(self.b, axis=-1) <= _TINY

    def _sqeuclidean(self):
        return np.maximum(self.get("aa") + self.get("bb") - 2.0 * self.get("ab"), 0.0)


def _fix_empty(s: np.ndarray, p: _Pair) -> np.ndarray:
    ea, eb = p.get("empty_a"), p.get("empty_b")
    s = np.where(ea & eb, 1.0, s)
    return np.where(ea ^ eb, 0.0, s)


def _fix_constant(s: np.ndarray, p: _Pair) -> np.ndarray:
    ca, cb = p.get("const_a"), p.get("const_b")
    same = np.abs(p.a - p.b).max(axis=-1) <= _TINY
    return np.where(ca | cb, np.where(ca & cb & same, 1.0, 0.0), s)


def _pearson_r(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    xm = x - x.mean(axis=-1, keepdims=True)
    ym = y - y.mean(axis=-1, keepdims=True)
    den = np.sqrt(_dot(xm, xm) * _dot(ym, ym))
    return np.clip(_safe_div(_dot(xm, ym), den, 0.0), -1.0, 1.0)


@njit(cache=True, nogil=True)
def _rank_rows(x, order, out):  # pragma: no cover - jit
    n, k = x.shape
    for r in range(n):
        i = 0
        while i < k:
            j = i
            v = x[r, order[r, i]]
            while j + 1 < k and x[r, order[r, j + 1]] == v:
                j += 1
            avg = 0.5 * (i + j) + 1.0
            for t in range(i, j + 1):
                out[r, order[r, t]] = avg
            i = j + 1


def average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..k along the last axis, ties get their average rank (float64).

    Equivalent to ``scipy.stats.rankdata(x, method="average", axis=-1)``.
    """
    x2 = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, x.shape[-1])
    out = np.empty_like(x2)
    _rank_rows(x2, np.argsort(x2, axis=-1), out)
    return out.reshape(x.shape)


@njit(cache=True, nogil=True)
def _kendall_rows(x, y, out):  # pragma: no cover - jit
    n, k = x.shape
    for r in range(n):
        nc = 0
        nd = 0
        tx = 0
        ty = 0
        for i in range(k - 1):
            xi = x[r, i]
            yi = y[r, i]
            for j in range(i + 1, k):
                dx = xi - x[r, j]
                dy = yi - y[r, j]
                if dx == 0.0:
                    tx += 1
                if dy == 0.0:
                    ty += 1
                if dx != 0.0 and dy != 0.0:
                    if (dx > 0.0) == (dy > 0.0):
                        nc += 1
                    else:
                        nd += 1
        n0 = k * (k - 1) // 2
        den = math.sqrt(float(n0 - tx) * float(n0 - ty))
        out[r] = (nc - nd) / den if den > 0.0 else 0.0


def _kendall_tau_b(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x2 = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, x.shape[-1])
    y2 = np.ascontiguousarray(y, dtype=np.float64).reshape(-1, y.shape[-1])
    out = np.empty(x2.shape[0], dtype=np.float64)
    _kendall_rows(x2, y2, out)
    return np.clip(out.reshape(x.shape[:-1]), -1.0, 1.0)


def _measure(p: _Pair, name: str) -> np.ndarray:
    a, b, k = p.a, p.b, p.k
    if name == "cosine":
        den = np.sqrt(p.get("aa") * p.get("bb"))
        return _fix_empty(_safe_div(p.get("ab"), den, 1.0), p)
    if name == "sqeuclidean":
        return 1.0 - p.get("sqeuclidean") / D_MAX[name](k)
    if name == "euclidean":
        return 1.0 - np.sqrt(p.get("sqeuclidean")) / D_MAX[name](k)
    if name == "l1":
        return 1.0 - p.get("absdiff") / D_MAX[name](k)
    if name == "sorensen":
        den = np.abs(a + b).sum(axis=-1)
        return 1.0 - _safe_div(p.get("absdiff"), den, 0.0)
    if name == "clark":
        num, den = np.abs(a - b), np.abs(a + b)
        ratio = np.divide(num, den, out=np.zeros_like(num), where=den > _TINY)
        return 1.0 - np.sqrt(_dot(ratio, ratio)) / D_MAX[name](k)
    if name == "hellinger":
        sa = np.abs(a).sum(axis=-1, keepdims=True)
        sb = np.abs(b).sum(axis=-1, keepdims=True)
        pa = np.sqrt(np.abs(a) / np.where(sa > _TINY, sa, 1.0))
        pb = np.sqrt(np.abs(b) / np.where(sb > _TINY, sb, 1.0))
        diff = pa - pb
        h = np.sqrt(_dot(diff, diff) / 2.0)
        return _fix_empty(1.0 - h / D_MAX[name](k), p)
    if name == "jaccard":
        den = p.get("aa") + p.get("bb") - p.get("ab")
        return _fix_empty(_safe_div(p.get("ab"), den, 1.0), p)
    if name == "dice":
        den = p.get("aa") + p.get("bb")
        return _fix_empty(_safe_div(2.0 * p.get("ab"), den, 1.0), p)
    if name == "pearson":
        return _fix_constant((_pearson_r(a, b) + 1.0) / 2.0, p)
    if name == "spearman":
        r = _pearson_r(average_ranks(a), average_ranks(b))
        return _fix_constant((r + 1.0) / 2.0, p)
    if name == "kendall":
        return _fix_constant((_kendall_tau_b(a, b) + 1.0) / 2.0, p)
    raise AnalysisError(f"unknown similarity measure {name!r}; use one of {', '.join(METRIC_NAMES)}.")


def _prepare(a: np.ndarray, b: np.ndarray) -> _Pair:
    a = np.asarray(a)
    b = np.asarray(b)
    if a.shape != b.shape:
        raise AnalysisError(
            f"block tensors differ in shape {a.shape} vs {b.shape}; compare images of the same size."
        )
    if a.ndim < 1 or a.shape[-1] < 2:
        raise AnalysisError(f"block tensors need a last axis of k >= 2 values, got shape {a.shape}.")
    if a.dtype.kind not in "uif" or b.dtype.kind not in "uif":
        raise AnalysisError("block tensors must be real numbers; pass HOG blocks from hog_blocks().")
    a = a.astype(np.float64, copy=False)
    b = b.astype(np.float64, copy=False)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise AnalysisError("block tensors contain NaN or infinite values; check the input images.")
    return _Pair(a, b)


def _finish(s: np.ndarray) -> np.ndarray:
    s = np.nan_to_num(np.asarray(s, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    return np.clip(s, 0.0, 1.0).astype(np.float32)


def similarity(a: np.ndarray, b: np.ndarray, metric: str = "cosine") -> np.ndarray:
    """Block-wise similarity of two HOG block tensors.

    Parameters
    ----------
    a, b : ndarray, shape (..., k)
        Block descriptors (typically (N, M, 36) from :func:`hog_blocks`),
        same shape, finite.
    metric : str
        One of :data:`METRIC_NAMES` (see the module table for definitions).

    Returns
    -------
    ndarray, shape (...), float32
        Similarity in [0, 1], 1 = identical, never NaN.

    References
    ----------
    Petsiuk & Pearce (2022), Table 2, eq. (4); Cha (2007).
    """
    if metric not in METRIC_NAMES:
        raise AnalysisError(f"unknown similarity measure {metric!r}; use one of {', '.join(METRIC_NAMES)}.")
    return _finish(_measure(_prepare(a, b), metric))


def similarity_all(
    a: np.ndarray, b: np.ndarray, metrics: tuple[str, ...] | list[str] = METRIC_NAMES
) -> dict[str, np.ndarray]:
    """All requested measures at once, sharing intermediate sums.

    Returns
    -------
    dict of str to ndarray, shape (...), float32
        ``{metric: similarity}`` in the order given.
    """
    for m in metrics:
        if m not in METRIC_NAMES:
            raise AnalysisError(f"unknown similarity measure {m!r}; use one of {', '.join(METRIC_NAMES)}.")
    p = _prepare(a, b)
    return {m: _finish(_measure(p, m)) for m in metrics}
