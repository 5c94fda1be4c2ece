"""Similarity measures vs independent per-block references (scipy)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats
from scipy.spatial import distance

from layerwatch.analysis.metrics import D_MAX, average_ranks, similarity, similarity_all
from layerwatch.analysis.settings import METRIC_NAMES
from layerwatch.errors import AnalysisError

K = 36


def _ref_one(x: np.ndarray, y: np.ndarray, name: str) -> float:
    """Independent per-block reference for well-posed (non-degenerate) inputs."""
    k = x.size
    if name == "cosine":
        return 1.0 - distance.cosine(x, y)
    if name == "sqeuclidean":
        return 1.0 - distance.sqeuclidean(x, y) / 2.0
    if name == "euclidean":
        return 1.0 - distance.euclidean(x, y) / math.sqrt(2.0)
    if name == "l1":
        return 1.0 - distance.cityblock(x, y) / math.sqrt(2.0 * k)
    if name == "sorensen":
        return 1.0 - distance.braycurtis(x, y)
    if name == "hellinger":
        p, q = x / x.sum(), y / y.sum()
        return 1.0 - distance.euclidean(np.sqrt(p), np.sqrt(q)) / math.sqrt(2.0)
    if name == "clark":
        t = [(abs(u - v) / (u + v)) ** 2 if u + v > 0 else 0.0 for u, v in zip(x, y, strict=True)]
        return 1.0 - math.sqrt(sum(t)) / math.sqrt(k)
    if name == "jaccard":
        d = distance.sqeuclidean(x, y)
        dot = float(np.dot(x, y))
        return dot / (d + dot)  # |x|^2 + |y|^2 - x.y = |x-y|^2 + x.y
    if name == "dice":
        d = distance.sqeuclidean(x, y)
        return 1.0 - d / (np.dot(x, x) + np.dot(y, y))
    if name == "pearson":
        return (stats.pearsonr(x, y).statistic + 1) / 2
    if name == "spearman":
        return (stats.spearmanr(x, y).statistic + 1) / 2
    if name == "kendall":
        return (stats.kendalltau(x, y, variant="b").statistic + 1) / 2
    raise KeyError(name)


def _unit_blocks(rng, n, k=K, ties=False):
    a = rng.random((n, k)) ** 3
    if ties:  # many exact zeros and repeated values, like sparse HOG blocks
        a = np.round(a * 4) / 4
        a[a.sum(axis=1) == 0, 0] = 1.0
    return a / np.linalg.norm(a, axis=1, keepdims=True)


@pytest.mark.parametrize("name", METRIC_NAMES)
@pytest.mark.parametrize("ties", [False, True])
def test_matches_scipy_per_block(name, ties):
    rng = np.random.default_rng(7)
    a = _unit_blocks(rng, 60, ties=ties)
    b = _unit_blocks(rng, 60, ties=ties)
    b[:10] = a[:10] + 0.01 * rng.random((10, K))  # near-identical pairs
    got = similarity(a.reshape(6, 10, K), b.reshape(6, 10, K), name).ravel()
    assert got.dtype == np.float32
    want = np.array([_ref_one(x, y, name) for x, y in zip(a, b, strict=True)])
    np.testing.assert_allclose(got, np.clip(want, 0, 1), atol=2e-6)


def test_average_ranks_match_rankdata():
    rng = np.random.default_rng(3)
    x = np.round(rng.random((50, K)) * 5)
    np.testing.assert_array_equal(average_ranks(x), stats.rankdata(x, method="average", axis=-1))


def test_distance_bounds_hold_for_hog_like_blocks():
    """d_max of eq. (4) bounds d for non-negative vectors of norm <= 1, and is reached."""
    rng = np.random.default_rng(5)
    a = _unit_blocks(rng, 300)
    b = _unit_blocks(rng, 300)
    # disjoint supports of equal size: the worst case for every distance
    a[:, K // 2 :] = 0
    b[:, : K // 2] = 0
    a[:, : K // 2] = 1.0
    b[:, K // 2 :] = 1.0
    a[150:] = _unit_blocks(rng, 150)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    ref = {
        "sqeuclidean": distance.sqeuclidean,
        "euclidean": distance.euclidean,
        "l1": distance.cityblock,
        "sorensen": distance.braycurtis,
        "hellinger": lambda x, y: distance.euclidean(np.sqrt(x / x.sum()), np.sqrt(y / y.sum())) / math.sqrt(2),
        "clark": lambda x, y: math.sqrt(sum(((u - v) / (u + v)) ** 2 for u, v in zip(x, y, strict=True) if u + v > 0)),
    }
    for name, fn in ref.items():
        d = np.array([fn(x, y) for x, y in zip(a, b, strict=True)])
        assert d.max() <= D_MAX[name](K) * (1 + 1e-12), name
        assert d[:150].max() == pytest.approx(D_MAX[name](K), rel=1e-9), name  # bound is tight
        assert similarity(a[:150], b[:150], name).max() == pytest.approx(0.0, abs=1e-6), name


# --------------------------------------------------------------- edge cases
EMPTY_BOTH_ONE = set(METRIC_NAMES)
ONE_EMPTY_ZERO = {"cosine", "jaccard", "dice", "hellinger", "sorensen", "pearson", "spearman", "kendall"}


@pytest.mark.parametrize("name", METRIC_NAMES)
def test_degenerate_blocks_defined_and_never_nan(name):
    rng = np.random.default_rng(11)
    v = _unit_blocks(rng, 1)[0]
    z = np.zeros(K)
    c = np.full(K, 1 / 6)  # constant, unit norm
    a = np.stack([z, z, v, c, c, v])
    b = np.stack([z, v, z, c, z, c])
    s = similarity(a, b, name)
    assert np.all(np.isfinite(s)) and s.min() >= 0 and s.max() <= 1
    assert s[0] == 1.0  # both empty: identical featureless areas
    if name in ONE_EMPTY_ZERO:
        assert s[1] == 0.0 and s[2] == 0.0
    else:  # distances keep their (finite) value, symmetric
        assert s[1] == s[2] and 0 <= s[1] < 1
    assert s[3] == pytest.approx(1.0, abs=1e-6)  # identical constant vectors
    if name in {"pearson", "spearman", "kendall"}:
        assert s[4] == 0.0 and s[5] == 0.0  # one constant: undefined -> 0


def test_bad_input_raises():
    with pytest.raises(AnalysisError):
        similarity(np.zeros((2, K)), np.zeros((3, K)))
    with pytest.raises(AnalysisError):
        similarity(np.full((2, K), np.nan), np.zeros((2, K)))
    with pytest.raises(AnalysisError):
        similarity(np.zeros((2, K)), np.zeros((2, K)), "nope")


def test_all_at_once_equals_one_by_one():
    rng = np.random.default_rng(2)
    a, b = _unit_blocks(rng, 40).reshape(4, 10, K), _unit_blocks(rng, 40).reshape(4, 10, K)
    allm = similarity_all(a, b)
    assert list(allm) == list(METRIC_NAMES)
    for name, s in allm.items():
        np.testing.assert_array_equal(s, similarity(a, b, name))


# ------------------------------------------------ paper Fig. 11 behaviour table
def _hist(center, width=2.0, k=K, level=0.0):
    x = np.arange(k)
    h = np.exp(-0.5 * ((x - center) / width) ** 2) + level
    return h / np.linalg.norm(h) * 0.9


# measure: (tolerates small noise, invariant to a level change, notices a shift)
# Measured behaviour, asserted so that a change shows up. Rank correlations and
# Clark (and Hellinger, through its square roots) are dominated by noise in near-empty bins; rank correlations barely
# notice a shifted peak because the long tails stay monotone.
FIG11 = {
    "cosine": (True, False, True),
    "sqeuclidean": (True, False, True),
    "pearson": (True, True, True),
    "spearman": (False, True, False),
    "kendall": (False, True, False),
    "jaccard": (True, False, True),
    "dice": (True, False, True),
    "l1": (True, False, True),
    "euclidean": (True, False, True),
    "hellinger": (False, False, True),
    "sorensen": (True, False, True),
    "clark": (False, False, True),
}


def test_figure11_cases():
    """Paper Fig. 11: identical, small deviations, level change, shifted, non-overlapping."""
    base = _hist(12)
    rng = np.random.default_rng(0)
    cases = {
        "identical": base,
        "small": np.clip(base + 0.01 * rng.standard_normal(K), 0, None),
        "level": base + 0.05,  # same shape, raised floor
        "shifted": _hist(16),
        "disjoint": _hist(30, width=1.0),
    }
    s = {c: {m: float(v[0]) for m, v in similarity_all(base[None], h[None]).items()} for c, h in cases.items()}
    assert set(FIG11) == set(METRIC_NAMES)
    for name, (small_ok, level_inv, sees_shift) in FIG11.items():
        assert s["identical"][name] == pytest.approx(1.0, abs=1e-6), name
        assert (s["small"][name] > 0.95) == small_ok, name
        assert (s["level"][name] > 0.99) == level_inv, name
        assert (s["shifted"][name] < 0.7) == sees_shift, name
        # non-overlapping histograms are never more similar than shifted ones
        assert s["disjoint"][name] < min(s["shifted"][name], 0.6), name
    for name in ("cosine", "jaccard", "dice", "hellinger", "sorensen"):  # no overlap -> 0
        assert s["disjoint"][name] < 1e-3, name


def test_unit_norm_blocks_make_cosine_dice_sqeuclidean_equal():
    rng = np.random.default_rng(9)
    a, b = _unit_blocks(rng, 50), _unit_blocks(rng, 50)
    s = similarity_all(a, b, ["cosine", "dice", "sqeuclidean", "euclidean"])
    np.testing.assert_allclose(s["dice"], s["cosine"], atol=1e-6)
    np.testing.assert_allclose(s["sqeuclidean"], s["cosine"], atol=1e-6)
    np.testing.assert_allclose(s["euclidean"], 1 - np.sqrt(1 - s["cosine"].astype(float)), atol=1e-5)


def test_never_nan_property():
    pytest.importorskip("hypothesis")
    from hypothesis import given, settings
    from hypothesis import strategies as st
    from hypothesis.extra.numpy import arrays

    values = st.sampled_from([0.0, 0.0, 0.2, 1 / 6, 0.5, 1.0, 1e-300, 3.0, -0.1])
    pair = arrays(np.float64, (2, 3, 12), elements=values)

    @settings(max_examples=60, deadline=None, database=None)
    @given(pair)
    def check(ab):
        for s in similarity_all(ab[0], ab[1]).values():
            assert np.all(np.isfinite(s)) and s.min() >= 0 and s.max() <= 1

    check()
