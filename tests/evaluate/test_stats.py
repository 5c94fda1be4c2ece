"""ROC AUC against brute-force pair counting; IoU, discriminative power, false-alarm bounds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from layerwatch.evaluate.stats import (
    discriminative_power,
    false_alarm_rate,
    iou,
    roc_auc,
    roc_curve,
)


def brute_auc(p, n) -> float:
    wins = sum(1.0 if a > b else 0.5 if a == b else 0.0 for a in p for b in n)
    return wins / (len(p) * len(n))


scores = st.lists(st.integers(0, 6).map(lambda v: v / 4.0), min_size=1, max_size=25)


@settings(max_examples=150, deadline=None)
@given(scores, scores)
def test_auc_equals_pair_counting_with_ties(p, n):
    assert roc_auc(p, n) == pytest.approx(brute_auc(p, n), abs=1e-12)


def test_auc_continuous_and_trapezoid():
    rng = np.random.default_rng(4)
    p, n = rng.normal(1, 1, 60), rng.normal(0, 1, 80)
    auc = roc_auc(p, n)
    assert auc == pytest.approx(brute_auc(p, n), abs=1e-12)
    fpr, tpr, _ = roc_curve(p, n)
    assert np.trapezoid(tpr, fpr) == pytest.approx(auc, abs=1e-9)


def test_auc_edge_cases():
    assert roc_auc([1, 2], [0]) == 1.0 and roc_auc([0], [1, 2]) == 0.0
    assert roc_auc([1, 1], [1]) == 0.5
    assert np.isnan(roc_auc([], [1])) and np.isnan(roc_auc([1], [np.nan]))


def test_iou():
    a = np.zeros((4, 4), bool)
    b = a.copy()
    assert iou(a, b) == 1.0
    a[:2] = True
    b[1:3] = True
    assert iou(a, b) == pytest.approx(4 / 12)


def test_discriminative_power_and_false_alarms():
    dp, d = discriminative_power([0.5, 0.7], [0.1, 0.1])
    assert dp == pytest.approx(50.0)
    assert d == pytest.approx(0.5 / np.sqrt(0.01 / 2))
    rate, up = false_alarm_rate(0, 1000)
    assert rate == 0 and up == pytest.approx(1000 * (1 - 0.05 ** (1 / 1000)), rel=1e-6)  # ~3/n
    rate, up = false_alarm_rate(2, 100)
    assert rate == 20 and 20 < up < 100
