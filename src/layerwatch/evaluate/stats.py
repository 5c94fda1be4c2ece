"""Detection statistics: ROC AUC, discriminative power, IoU, false-alarm rates.

Definitions used in the evaluation report
-----------------------------------------
* **ROC AUC** of a score ``s`` (here the layer's anomaly ratio a%) between
  positives ``P`` (layers with a failure present) and negatives ``N`` (clean
  layers): the probability that a random positive scores higher than a
  random negative, ties counting one half (Mann-Whitney U / (|P| |N|)).
  Computed from average ranks in ``O((P + N) log(P + N))``.
* **Discriminative power** (the paper's Fig. 14 compares measures by how far
  apart a% lies on failed and normal layers): we report
  ``DP = mean(a%_failed) - mean(a%_clean)`` in percentage points, and its
  standardised form ``d' = DP / sqrt((var_failed + var_clean) / 2)``
  (Cohen's d), which does not reward a measure that merely inflates every a%.
* **IoU** of two boolean masks: ``|A & B| / |A | B|`` (1 when both are empty).
* **False alarms per 1000 clean layers** with a one-sided 95 % upper bound
  (exact binomial / Clopper-Pearson; ``3/n`` when none are seen).

References
----------
Petsiuk & Pearce (2022), Fig. 14; Hanley & McNeil (1982) for AUC = U / (P N).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import beta, rankdata

__all__ = ["roc_auc", "roc_curve", "discriminative_power", "iou", "false_alarm_rate"]


def roc_auc(positives, negatives) -> float:
    """Area under the ROC curve of scores ``positives`` vs ``negatives`` (ties = 1/2).

    Parameters
    ----------
    positives, negatives : array_like, shape (P,), (N,)
        Scores; higher means "more likely failed". NaNs are dropped.

    Returns
    -------
    float
        AUC in [0, 1]; NaN when either group is empty.
    """
    p = np.asarray(positives, np.float64).ravel()
    n = np.asarray(negatives, np.float64).ravel()
    p, n = p[np.isfinite(p)], n[np.isfinite(n)]
    if p.size == 0 or n.size == 0:
        return float("nan")
    ranks = rankdata(np.concatenate([p, n]))  # average ranks for ties
    u = ranks[: p.size].sum() - p.size * (p.size + 1) / 2.0
    return float(u / (p.size * n.size))


def roc_curve(positives, negatives) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ROC points for thresholds ``score > t``.

    Returns
    -------
    fpr, tpr, thresholds : ndarray
        Sorted by increasing ``fpr``; ``thresholds[k]`` gives ``(fpr[k], tpr[k])``.
    """
    p = np.asarray(positives, np.float64)
    n = np.asarray(negatives, np.float64)
    t = np.unique(np.concatenate([p, n, [-np.inf]]))[::-1]
    tpr = np.array([(p > x).mean() if p.size else np.nan for x in t])
    fpr = np.array([(n > x).mean() if n.size else np.nan for x in t])
    return fpr, tpr, t


def discriminative_power(failed, clean) -> tuple[float, float]:
    """``(DP, d')``: difference of means in percentage points and its standardised form."""
    f = np.asarray(failed, np.float64)
    c = np.asarray(clean, np.float64)
    if f.size == 0 or c.size == 0:
        return float("nan"), float("nan")
    dp = 100.0 * (f.mean() - c.mean())
    sd = np.sqrt((f.var() + c.var()) / 2.0)
    return float(dp), float(100.0 * (f.mean() - c.mean()) / (100.0 * sd)) if sd > 0 else float("inf")


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks of the same shape (1.0 when both empty)."""
    a = np.asarray(a, bool)
    b = np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else float(np.count_nonzero(a & b) / union)


def false_alarm_rate(alarms: int, n_clean: int) -> tuple[float, float]:
    """``(rate, upper95)`` false alarms per 1000 clean layers (one-sided 95 % Clopper-Pearson bound)."""
    if n_clean <= 0:
        return float("nan"), float("nan")
    rate = 1000.0 * alarms / n_clean
    upper = 1.0 if alarms >= n_clean else float(beta.ppf(0.95, alarms + 1, n_clean - alarms))
    return float(rate), float(1000.0 * upper)
