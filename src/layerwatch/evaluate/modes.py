"""The evaluation by mode: single-photo (bed photo only) against series (the print's own history).

Every simulated layer photo of :func:`~layerwatch.evaluate.harness.run_evaluation`
goes through two pipelines when the scene channel is on:

* **series** (what the monitor runs): one pipeline per print, fed the print's
  photos in order; the scene channel's expected appearance follows the
  print, the failure typer sees the previous photo's regions;
* **single photo**: the pipeline forgets everything before each photo
  (:meth:`~layerwatch.pipeline.step.LayerPipeline.new_print` with the
  empty-bed photo): the photo is judged against its rendered reference and
  the empty bed only.

For each mode and photo :func:`mode_score` keeps the *whole-view score*
(:func:`~layerwatch.analysis.scoring.whole_view_score`: a% of eq. 5 plus the
area changed beside the printed layer and a moved part's blocks beside its
footprint, over the printed area), the IoU of what the layer's result marks (HOG blocks below
T_S and the scene channel's region boxes; a moved part's outline and a
foreign body's own pixels instead of their regions' blocks) with the simulator's failed
region, the kind of the region that covers the failure best (the confusion
matrix) and, for a moved part, the error of the reported displacement.
:func:`summarize_modes` turns them into the report's figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from layerwatch.analysis.block_masks import block_tiles, touching
from layerwatch.analysis.failure_kinds import FAILURE_KINDS, MOVED_KINDS
from layerwatch.analysis.overlay import anomalous_blocks
from layerwatch.analysis.region_outline import outline_mask, region_box
from layerwatch.analysis.result import LayerResult, Region
from layerwatch.analysis.scoring import whole_view_score
from layerwatch.evaluate.stats import iou, roc_auc
from layerwatch.geometry.topview import TopView

__all__ = ["MISSED", "MODES", "ModeScore", "mode_score", "summarize_modes"]

#: the evaluation's modes, in report order
MODES = ("single", "series")
#: the confusion matrix's column for a failure that no region covers
MISSED = "missed"


@dataclass
class ModeScore:
    """One photo's figures in one mode.

    Attributes
    ----------
    score : float
        Whole-view score (:func:`~layerwatch.analysis.scoring.whole_view_score`): a% plus the scene
        channel's change beside the print and a moved part's blocks beside its footprint, over ``S_P``.
    iou : float or None
        IoU of the marked area with the failed region (failed photos only).
    kind : str
        Kind of the region covering the failure best; :data:`MISSED` when none
        covers it; ``""`` on clean photos.
    confidence : float
        That region's ``kind_confidence``.
    displacement_error_mm : float or None
        ``|reported - true|`` displacement, mm, when the failure moved the part
        and its region reports a displacement.
    status : str
        The pipeline's status for the photo (``"ok"`` or ``"error"``).
    """

    score: float
    iou: float | None = None
    kind: str = ""
    confidence: float = 0.0
    displacement_error_mm: float | None = None
    status: str = "ok"


def _box(r: Region, topview: TopView, shape: tuple[int, int]) -> tuple[slice, slice]:
    return region_box(r.bbox_mm, topview, shape) or (slice(0, 0), slice(0, 0))


def marked_area(res: LayerResult, topview: TopView) -> np.ndarray:
    """Top-view pixels the result marks, bool (H, W).

    The tiles of the anomalous HOG blocks and the boxes of the regions
    beside the print; a region with an outline (a moved part, a foreign body:
    :attr:`~layerwatch.analysis.result.Region.outline_mm`) marks its outline
    instead of its box and of the tiles inside its box. A moved part's outline
    (layer shift, detachment) also stands for the tiles connected to its
    regions' boxes (8-connected): the hysteresis growth of its blocks, which
    follows the moved part's walls and lower layers beyond the boxes.
    """
    shape = (int(topview.shape[0]), int(topview.shape[1]))
    out = np.zeros(shape, bool)
    if res.heatmap is not None and res.grid is not None:
        out |= block_tiles(anomalous_blocks(res), shape, res.grid.cell_px, res.grid.block_cells, fill=False)
    outlined = [r for r in [*res.regions, *res.outside_regions] if r.outline_mm]
    moved = np.zeros(shape, bool)
    for r in outlined:
        if r.kind in MOVED_KINDS:
            moved[_box(r, topview, shape)] = True
    out &= ~touching(out, moved)
    for r in outlined:
        out[_box(r, topview, shape)] = False
    for r in res.outside_regions:
        if not r.outline_mm:
            out[_box(r, topview, shape)] = True
    for outline in dict.fromkeys(r.outline_mm for r in outlined):
        out |= outline_mask(outline, topview)
    return out


def mode_score(res: LayerResult, truth: np.ndarray | None, topview: TopView,
               true_offset_mm: np.ndarray | None = None) -> ModeScore:
    """The figures of one analysed photo in one mode (see :class:`ModeScore`).

    Parameters
    ----------
    res : LayerResult
        The pipeline's result for the photo (typed regions).
    truth : ndarray, bool, shape topview.shape, or None
        The simulator's failed region; None on a clean photo.
    topview : TopView
    true_offset_mm : ndarray, shape (2,), optional
        The simulated displacement of a layer shift or detachment, bed mm.
    """
    if res.status != "ok":
        return ModeScore(float("nan"), status=res.status)
    score = whole_view_score(res)
    if truth is None:
        return ModeScore(score)
    shape = (int(topview.shape[0]), int(topview.shape[1]))
    best, best_px = None, 0
    for r in [*res.regions, *res.outside_regions]:
        px = int(np.count_nonzero(truth[_box(r, topview, shape)]))
        if px > best_px:
            best, best_px = r, px
    out = ModeScore(score, iou=iou(marked_area(res, topview), truth), kind=MISSED)
    if best is not None:
        out.kind, out.confidence = best.kind or "unknown", float(best.kind_confidence)
        if true_offset_mm is not None and best.displacement_mm is not None:
            out.displacement_error_mm = float(np.hypot(*(np.asarray(best.displacement_mm) - true_offset_mm)))
    return out


def _since_table(score: np.ndarray, kinds: np.ndarray, since: np.ndarray, types: tuple[str, ...]) -> dict:
    clean = score[kinds == "clean"]
    return {t: [(int(d), int(((kinds == t) & (since == d)).sum()), roc_auc(score[(kinds == t) & (since == d)], clean))
                for d in sorted(set(since[kinds == t].tolist()))] for t in types}


def summarize_modes(records: list, min_iou_size_mm: float) -> dict:
    """Per mode: AUROC per type of the whole-view score, by layers since onset, IoU, confusion matrix, displacement.

    Parameters
    ----------
    records : list of LayerRecord
        Records with ``modes`` filled (:func:`~layerwatch.evaluate.harness.run_evaluation`).
    min_iou_size_mm : float
        Failures at least this large count in the IoU. A layer shift's or a
        detachment's size is its displacement, but its failed region is the
        layer's whole outline (tens of mm): those always count.

    Returns
    -------
    dict
        ``{mode: {"auroc": {type: float}, "since": {type: [(d, n, auroc)]}, "iou": {type: (mean, n)},
        "confusion": {type: {kind: count}}, "kinds": [columns], "displacement": {type: [errors mm]},
        "n_clean": int, "errors": int}}`` for the modes present in the records.
    """
    out: dict = {}
    kinds = np.array([r.kind for r in records])
    types = tuple(dict.fromkeys(k for k in kinds if k != "clean"))
    since = np.array([r.since_onset for r in records])
    for mode in MODES:
        have = [mode in r.modes for r in records]
        if not records or not all(have):
            continue
        ms = [r.modes[mode] for r in records]
        score = np.array([m.score for m in ms], float)
        clean = score[kinds == "clean"]
        columns = [k for k in FAILURE_KINDS if k != "nothing_extruded"] + [MISSED]
        conf = {t: {k: 0 for k in columns} for t in types}
        disp: dict[str, list[float]] = {t: [] for t in types if t in MOVED_KINDS}
        ious: dict[str, list[float]] = {t: [] for t in types}
        for r, m in zip(records, ms, strict=True):
            if r.kind == "clean" or m.status != "ok":
                continue
            conf[r.kind][m.kind if m.kind in conf[r.kind] else "unknown"] += 1
            if r.kind in disp and m.displacement_error_mm is not None:
                disp[r.kind].append(m.displacement_error_mm)
            if m.iou is not None and (r.size_mm >= min_iou_size_mm or r.kind in MOVED_KINDS):
                ious[r.kind].append(m.iou)
        out[mode] = {
            "auroc": {t: roc_auc(score[kinds == t], clean) for t in types},
            "since": _since_table(score, kinds, since, types),
            "iou": {t: (float(np.mean(v)) if v else float("nan"), len(v)) for t, v in ious.items()},
            "confusion": conf, "kinds": columns, "displacement": disp,
            "n_clean": int(np.isfinite(clean).sum()), "errors": int(sum(m.status != "ok" for m in ms)),
        }
    return out
