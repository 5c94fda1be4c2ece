"""Turn evaluation records into per-measure, per-failure-type figures and a recommendation.

Choice of the recommended setting. For each measure and block threshold
``T_S`` the layer score is a%, and the pause ratio is set just above the
highest a% seen on any clean layer (x 1.1, at least 2 %), so the sample has
no false alarm. Each measure gets the ``T_S`` with the highest mean detection
rate over the failure types at that pause ratio (ties: higher worst-type ROC
AUC); the recommended measure is the best of those. Ranking by AUROC alone
favours thresholds where every layer, clean or not, has a high a% and no
usable pause ratio exists; ranking by detection at zero false alarms is what
a monitor needs. The report gives AUROC, the detection rate per type and the
Clopper-Pearson bound on the false-alarm rate the sample size allows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import cast

import numpy as np

from layerwatch.evaluate.harness import EvalData
from layerwatch.evaluate.modes import summarize_modes
from layerwatch.evaluate.stats import discriminative_power, false_alarm_rate, roc_auc
from layerwatch.simulate import FAILURE_TYPES

__all__ = ["IOU_MIN_SIZE_MM", "Summary", "at_setting", "summarize"]

#: failures at least this large (mm) are scored for localisation IoU (the issue's ">= 5 mm")
IOU_MIN_SIZE_MM = 5.0


@dataclass
class Summary:
    """Figures of an evaluation (arrays indexed [measure, type] unless said otherwise)."""

    metrics: tuple[str, ...]
    types: tuple[str, ...]
    thresholds: np.ndarray
    n_clean: int
    n_failed: dict[str, int]
    auc: np.ndarray            # (M, K, T) AUROC per measure, type, block threshold
    best_t: np.ndarray         # (M,) index of each measure's best threshold (mean detection)
    a_failed: np.ndarray       # (M, K) mean a% on failed layers at the measure's best T
    a_clean: np.ndarray        # (M,) mean a% on clean layers at the measure's best T
    dp: np.ndarray             # (M, K) discriminative power (percentage points)
    dprime: np.ndarray         # (M, K) standardised
    iou: np.ndarray            # (M, K) mean IoU on failed layers with size >= 5 mm
    iou_all: np.ndarray        # (M, K) mean IoU on all failed layers
    iou_best: np.ndarray       # (M, K) best mean IoU (size >= 5 mm) over all T_S
    fa_rate: np.ndarray        # (M,) false alarms / 1000 clean layers at the measure's pause ratio
    pause_ratio: np.ndarray    # (M,)
    tpr: np.ndarray            # (M, K) share of failed layers above the pause ratio
    rec_metric: int
    rec_t: int
    fa_upper: float
    clean_block_share: float   # share of clean printed-area blocks with cosine > 0.7
    clean_flat_share: float    # share of those blocks featureless in both images (similarity 1 by rule)
    clean_textured_share: float  # share above cosine 0.7 among the blocks that are not featureless
    auc_region: np.ndarray     # (M, K) AUROC of the largest-region area at the measure's best T
    scores: dict               # raw a% arrays of the recommended setting: {"clean": ..., type: ...}
    auc_since: dict            # recommended setting: {type: [(layers since onset, n layers, AUROC), ...]}
    auc_surface: dict = field(default_factory=dict)  # recommended setting: {type: [(surface under the failure, n layers, AUROC), ...]}
    modes: dict = field(default_factory=dict)  # configured setting per mode (:func:`~layerwatch.evaluate.modes.summarize_modes`)
    #: simulated prints (scenarios) behind each type's failed layers: the layers of one print share one failure,
    #: so this, not ``n_failed``, is the sample an AUROC rests on
    n_prints: dict = field(default_factory=dict)


def _auc_region(recs: list, kinds: np.ndarray, types: tuple[str, ...], best_t: np.ndarray) -> np.ndarray:
    """(M, K) AUROC with the largest anomalous region (mm^2) as the layer score, each measure at its best T_S."""
    auc_region = np.full((len(best_t), len(types)), np.nan)
    if recs and all(r.region is not None for r in recs):
        G = np.stack([r.region for r in recs])
        clean = kinds == "clean"
        for m in range(len(best_t)):
            for k, t in enumerate(types):
                auc_region[m, k] = roc_auc(G[kinds == t, m, best_t[m]], G[clean, m, best_t[m]])
    return auc_region


def _auc_breakdowns(recs: list, a: np.ndarray, kinds: np.ndarray, types: tuple[str, ...]) -> tuple[dict, dict]:
    """AUROC of one setting's a% (``a``, one per record) by layers since the onset and by the surface under the failure.

    Returns ``({type: [(depth, n, auroc)]}, {type: [(surface, n, auroc)]})`` against all clean layers.
    """
    clean = kinds == "clean"
    since = np.array([r.since_onset for r in recs])
    auc_since: dict = {}
    for t in types:
        rows = []
        for d in sorted(set(since[kinds == t].tolist())):
            sel = (kinds == t) & (since == d)
            rows.append((int(d), int(sel.sum()), roc_auc(a[sel], a[clean])))
        auc_since[t] = rows
    surf = np.array([r.surface for r in recs])
    auc_surface: dict = {}
    for t in types:
        auc_surface[t] = [(c, int(((kinds == t) & (surf == c)).sum()), roc_auc(a[(kinds == t) & (surf == c)], a[clean]))
                          for c in ("solid", "sparse", "walls", "none") if ((kinds == t) & (surf == c)).any()]
    return auc_since, auc_surface


def summarize(data: EvalData) -> Summary:
    """Compute every figure of the report from the records."""
    recs = data.records
    metrics, T = data.metrics, data.thresholds
    A = np.stack([r.a for r in recs]) if recs else np.zeros((0, len(metrics), len(T)))
    kinds = np.array([r.kind for r in recs])
    types = tuple(t for t in FAILURE_TYPES if (kinds == t).any())
    clean = kinds == "clean"
    M, K, NT = len(metrics), len(types), len(T)
    auc = np.full((M, K, NT), np.nan)
    for k, t in enumerate(types):
        pos = kinds == t
        for m in range(M):
            for j in range(NT):
                auc[m, k, j] = roc_auc(A[pos, m, j], A[clean, m, j])
    worst = np.nanmin(auc, axis=1) if K else np.zeros((M, NT))
    c_all = A[clean]
    pause_mt = np.minimum(np.maximum(0.02, 1.1 * c_all.max(axis=0)), 1.0) if c_all.size else np.full((M, NT), 0.1)
    det = np.zeros((M, NT))
    for t in types:
        det += (A[kinds == t] > pause_mt[None]).mean(axis=0) / max(K, 1)
    best_t = np.array([int(np.lexsort((-worst[m], -det[m]))[0]) for m in range(M)])
    a_failed = np.full((M, K), np.nan)
    a_clean = np.zeros(M)
    dp = np.full((M, K), np.nan)
    dprime = np.full((M, K), np.nan)
    iou = np.full((M, K), np.nan)
    iou_all = np.full((M, K), np.nan)
    iou_best = np.full((M, K), np.nan)
    tpr = np.full((M, K), np.nan)
    pause = np.zeros(M)
    fa = np.zeros(M)
    big = np.array([r.size_mm >= IOU_MIN_SIZE_MM and r.iou is not None for r in recs])
    for m in range(M):
        j = best_t[m]
        c = A[clean, m, j]
        a_clean[m] = c.mean() if c.size else np.nan
        pause[m] = pause_mt[m, j]
        fa[m] = false_alarm_rate(int((c > pause[m]).sum()), int(c.size))[0]
        for k, t in enumerate(types):
            f = A[kinds == t, m, j]
            a_failed[m, k] = f.mean()
            dp[m, k], dprime[m, k] = discriminative_power(f, c)
            tpr[m, k] = (f > pause[m]).mean()
            sel = (kinds == t) & big
            if sel.any():
                per_t = np.mean([cast(np.ndarray, recs[i].iou)[m] for i in np.flatnonzero(sel)], axis=0)
                iou[m, k] = float(per_t[j])
                iou_best[m, k] = float(per_t.max())
            sel = (kinds == t) & np.array([r.iou is not None for r in recs])
            if sel.any():
                iou_all[m, k] = float(np.mean([cast(np.ndarray, recs[i].iou)[m, j] for i in np.flatnonzero(sel)]))
    order = np.lexsort((-np.array([worst[m, best_t[m]] for m in range(M)]),
                        -np.array([det[m, best_t[m]] for m in range(M)])))
    rec = int(order[0]) if M else 0
    auc_region = _auc_region(recs, kinds, types, best_t)
    n_clean = int(clean.sum())
    fa_upper = false_alarm_rate(0, n_clean)[1] if n_clean else float("nan")
    hi = sum(r.clean_high[0] for r in recs if r.kind == "clean")
    tot = sum(r.clean_high[1] for r in recs if r.kind == "clean")
    flat = sum(r.clean_high[2] for r in recs if r.kind == "clean")
    jr = best_t[rec]
    scores = {"clean": A[clean, rec, jr]}
    for t in types:
        scores[t] = A[kinds == t, rec, jr]
    auc_since, auc_surface = _auc_breakdowns(recs, A[:, rec, jr], kinds, types)
    return Summary(
        metrics=tuple(metrics), types=types, thresholds=T, n_clean=n_clean,
        n_failed={t: int((kinds == t).sum()) for t in types}, auc=auc, best_t=best_t,
        n_prints={t: len({r.scenario for r in recs if r.kind == t}) for t in types},
        a_failed=a_failed, a_clean=a_clean, dp=dp, dprime=dprime, iou=iou, iou_all=iou_all, iou_best=iou_best, fa_rate=fa,
        pause_ratio=pause, tpr=tpr, rec_metric=rec, rec_t=int(jr), fa_upper=fa_upper,
        clean_block_share=hi / tot if tot else float("nan"), scores=scores,
        clean_flat_share=flat / tot if tot else float("nan"),
        clean_textured_share=(hi - flat) / (tot - flat) if tot > flat else float("nan"),
        auc_region=auc_region, auc_since=auc_since, auc_surface=auc_surface,
        modes=summarize_modes(recs, IOU_MIN_SIZE_MM),
    )


def at_setting(data: EvalData, metric: str, threshold: float, pause_ratio: float) -> dict | None:
    """Figures of one fixed setting on the sample: the one a job would run with, chosen elsewhere.

    :func:`summarize` picks the setting that suits *this* sample best; on
    another part the question is how the configured setting (the evaluation's
    recommendation for the example part, or the job file's) does.

    Parameters
    ----------
    data : EvalData
    metric : str
        Measure name (one of ``data.metrics``).
    threshold : float
        Block threshold T_S; must be one of ``data.thresholds``.
    pause_ratio : float
        a% (0-1) above which a layer alarms.

    Returns
    -------
    dict or None
        ``metric``, ``threshold``, ``pause_ratio``, ``n_clean``, ``clean_above`` (clean layers above
        the pause ratio), ``max_clean`` (highest clean a%), and per failure type ``{type: (n layers,
        AUROC, share above the pause ratio, mean IoU of failures >= 5 mm or nan)}`` under ``types``;
        ``whole_view``: per failure type the AUROC of the whole-view score (``S_A`` plus the scene
        channel's change beside the print, over ``S_P``) and ``clean_outside``, the clean layers
        with any such change (both only when the scene channel ran);
        None when the measure or T_S was not scored.
    """
    if metric not in data.metrics or not data.records:
        return None
    hit = np.flatnonzero(np.isclose(data.thresholds, threshold))
    if hit.size == 0:
        return None
    m, j = data.metrics.index(metric), int(hit[0])
    recs = data.records
    a = np.array([r.a[m, j] for r in recs])
    kinds = np.array([r.kind for r in recs])
    clean = a[kinds == "clean"]
    types = {}
    for t in FAILURE_TYPES:
        sel = kinds == t
        if not sel.any():
            continue
        big = [r.iou[m, j] for r in recs if r.kind == t and r.iou is not None and r.size_mm >= IOU_MIN_SIZE_MM]
        types[t] = (int(sel.sum()), roc_auc(a[sel], clean), float((a[sel] > pause_ratio).mean()),
                    float(np.mean(big)) if big else float("nan"))
    out = {"metric": metric, "threshold": float(data.thresholds[j]), "pause_ratio": float(pause_ratio),
           "n_clean": int(clean.size), "clean_above": int((clean > pause_ratio).sum()),
           "max_clean": float(clean.max()) if clean.size else float("nan"), "types": types}
    if data.setup.get("scene"):
        outside = np.array([r.outside_mm2 for r in recs])
        printed = np.array([max(r.printed_mm2, 1.0) for r in recs])
        whole = a + outside / printed
        out["whole_view"] = {t: roc_auc(whole[kinds == t], whole[kinds == "clean"]) for t in types}
        out["clean_outside"] = int((outside[kinds == "clean"] > 0).sum())
    return out
