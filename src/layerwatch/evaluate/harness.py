"""Run simulated prints through the pipeline and score every measure at every block threshold.

Every simulated layer photo goes through the per-layer step the monitor runs
(:meth:`~layerwatch.pipeline.step.LayerPipeline.process`: warp, reference,
comparison with the configured measure); the sweep then scores, from the
HOG blocks of the same top view and reference, each of the twelve measures
at each block threshold ``T_S`` of :data:`THRESHOLDS`:

* the anomaly ratio a% (eq. 5) over the considered blocks;
* for layers with a failure, the pixel IoU between the anomalous blocks'
  tiles and the simulator's failed region (``SimFrame.truth_area``).

Sampling. Single-failure scenarios (:func:`~layerwatch.simulate.random_scenarios`)
contribute the layer before the onset (a clean negative) and ``frames_after``
layers from the onset; clean control prints contribute layers spread over
the whole height. Every photo gets its own camera/lighting noise.

References
----------
Petsiuk & Pearce (2022), Section 3, Figs. 13-15.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from layerwatch.analysis.metrics import similarity_all
from layerwatch.analysis.result import LayerResult
from layerwatch.analysis.scoring import (
    anomaly_ratio,
    area_weight,
    block_hogs,
    grow_regions,
    growth_reach,
    tile_share,
)
from layerwatch.analysis.settings import METRIC_NAMES
from layerwatch.errors import AnalysisError
from layerwatch.evaluate.modes import MODES, ModeScore, mode_score
from layerwatch.evaluate.parallel import map_prints
from layerwatch.gcode.toolpath import FEATURES, Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.policy import PausePolicy, layer_alarm
from layerwatch.pipeline.step import LayerPipeline, judge_layers
from layerwatch.simulate import (
    FAILURE_TYPES,
    PrintSimulator,
    Scenario,
    SimSettings,
    patch_layers,
    random_scenarios,
)
from layerwatch.simulate.failures import has_thin_walls, resolve
from layerwatch.simulate.parts import window_part

__all__ = ["THRESHOLDS", "LayerRecord", "EvalData", "plan_frames", "run_evaluation", "score_layer", "surface_under",
           "tile_fraction"]

#: block thresholds T_S scanned for every measure
THRESHOLDS = np.round(np.arange(0.05, 0.901, 0.05), 2)


@dataclass
class LayerRecord:
    """Scores of one simulated layer photo.

    Attributes
    ----------
    scenario : str
    kind : str
        Failure type present in the photo, or ``"clean"``.
    layer : int
    size_mm : float
        Failure size (0 for clean).
    a : ndarray, shape (12, T), float32
        a% per measure (:data:`METRIC_NAMES` order) and threshold (:data:`THRESHOLDS`).
    iou : ndarray, shape (12, T), float32, or None
        Pixel IoU of anomalous tiles vs ``truth_area`` (failed layers only).
    clean_high : tuple of int
        ``(blocks on printed area with cosine > 0.7, blocks on printed area, of
        those the blocks featureless in both images)`` (clean layers only).
    region : ndarray, shape (12, T), float32, or None
        Area of the largest 8-connected group of anomalous blocks, mm^2 (a layer
        score that small local defects on large layers do not dilute).
    since_onset : int
        Layers printed since the failure's onset (0 = the onset layer); for a patch failure, its
        layers that removed beads since the onset (:func:`~layerwatch.simulate.failures.patch_layers`);
        -1 for clean layers.
    surface : str
        What the layer's plan prints where the failure is (:func:`surface_under`):
        ``"solid"``, ``"sparse"``, ``"walls"`` or ``"none"``; ``""`` for clean layers.
    outside_mm2 : float
        The scene channel's change beside the printed layer (``LayerResult.outside_anomalous_mm2``), mm^2;
        0 when the channel is off.
    printed_mm2 : float
        The layer's printed area ``S_P`` (eq. 5), mm^2.
    modes : dict of str to ModeScore
        The photo's whole-view score, IoU, failure kind and displacement error in each mode
        (:mod:`layerwatch.evaluate.modes`: ``"series"``, ``"single"``).
    """

    scenario: str
    kind: str
    layer: int
    size_mm: float
    a: np.ndarray
    iou: np.ndarray | None = None
    clean_high: tuple[int, ...] = (0, 0, 0)
    region: np.ndarray | None = None
    since_onset: int = -1
    surface: str = ""
    outside_mm2: float = 0.0
    printed_mm2: float = 0.0
    modes: dict[str, ModeScore] = field(default_factory=dict)


#: toolpath features counted as a solid surface / as sparse infill by :func:`surface_under`
SOLID_FEATURES = ("solid_infill", "top_solid_infill", "bridge")
SPARSE_FEATURES = ("infill",)


def surface_under(tp: Toolpath, index: int, mask: np.ndarray, topview) -> str:
    """What layer ``index`` of the plan prints inside ``mask``: ``"solid"``, ``"sparse"``, ``"walls"`` or ``"none"``.

    The majority class of the layer's segments whose midpoints fall in the
    top-view ``mask`` (solid/top/bridge infill, sparse infill, anything else);
    ``"none"`` when no segment does (beside the part). Missing sparse infill shows the same
    pattern one layer lower, a hole in a solid layer shows the layer below, so
    detection differs by class (the report splits AUROC by it).
    """
    sl = tp.layer_slice(index)
    mid = 0.5 * (tp.start[sl] + tp.end[sl])
    uv = np.round(topview.to_px(mid)).astype(int)
    h, w = mask.shape
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    inside = np.zeros(len(mid), bool)
    inside[ok] = mask[uv[ok, 1], uv[ok, 0]]
    feats = tp.feature[sl][inside]
    if feats.size == 0:
        return "none"
    solid = int(np.isin(feats, [FEATURES.index(n) for n in SOLID_FEATURES]).sum())
    sparse = int(np.isin(feats, [FEATURES.index(n) for n in SPARSE_FEATURES]).sum())
    other = feats.size - solid - sparse
    return max((solid, "solid"), (sparse, "sparse"), (other, "walls"))[1]


@dataclass
class EvalData:
    """All records of an evaluation run plus its set-up."""

    records: list[LayerRecord] = field(default_factory=list)
    metrics: tuple[str, ...] = METRIC_NAMES
    thresholds: np.ndarray = field(default_factory=lambda: THRESHOLDS.copy())
    setup: dict = field(default_factory=dict)
    seconds: float = 0.0
    errors: list[str] = field(default_factory=list)


def tile_fraction(mask: np.ndarray, n: int, m: int, cell_px: int, block_cells: int) -> np.ndarray:
    """Share of each block's tile (its central cell) covered by ``mask``, shape (n, m) float32."""
    off = (block_cells - 1) * cell_px // 2
    c = cell_px
    sub = np.zeros((n * c, m * c), np.float32)
    h = min(n * c, mask.shape[0] - off)
    w = min(m * c, mask.shape[1] - off)
    sub[:h, :w] = mask[off : off + h, off : off + w]
    return sub.reshape(n, c, m, c).mean(axis=(1, 3))


def plan_frames(tp: Toolpath, n_layers: int, seed: int = 0, frames_after: int = 3,
                clean_share: float = 0.4, beside_share: float = 0.0) -> list[tuple[Scenario, list[int]]]:
    """Scenarios and the layers to photograph in each, about ``n_layers`` frames in all.

    ``beside_share`` of the foreign bodies and spaghetti lie on the bed beside the part.

    A patch failure (``infill_defect``, ``thin_wall``) is photographed on the first
    ``frames_after`` layers on which it removes beads (:func:`~layerwatch.simulate.failures.patch_layers`):
    a layer that prints nothing inside the patch (another object's layer of a plate printed in
    turns, a layer between two of sparse infill printed every other layer) differs from its plan
    nowhere, so it is neither a failed photo nor a clean one.

    Returns
    -------
    list of (Scenario, list of int)
    """
    per_fail = frames_after + 1
    n_clean_frames = int(round(n_layers * clean_share))
    n_fail = max(len(FAILURE_TYPES), int(round((n_layers - n_clean_frames) / per_fail)))
    plan = []
    for s in random_scenarios(tp, n_fail, seed=seed, clean_fraction=0.0, beside_fraction=beside_share):
        if not s.failures:  # a type no layer of this part can take (run_evaluation says which)
            continue
        f = s.failures[0]
        last = tp.n_layers - 1
        patch = patch_layers(resolve(f, tp), tp) if f.type in ("infill_defect", "thin_wall") else []
        after = patch[:frames_after] or [min(f.onset + k, last) for k in range(frames_after)]
        layers = sorted({max(f.onset - 1, 0), *after})
        plan.append((s, layers))
    rng = np.random.default_rng(seed + 1)
    per_clean = max(4, min(12, tp.n_layers // 2))
    k = 0
    while n_clean_frames > 0:
        take = min(per_clean, n_clean_frames)
        layers = sorted(rng.choice(np.arange(1, tp.n_layers), size=min(take, tp.n_layers - 1), replace=False).tolist())
        plan.append((Scenario((), name=f"clean{k:02d}"), layers))
        n_clean_frames -= len(layers)
        k += 1
    return plan


def _largest(anom: np.ndarray) -> int:
    lab, n = ndimage.label(anom, structure=np.ones((3, 3), bool))
    return int(np.bincount(lab.ravel())[1:].max()) if n else 0


def _score(res: LayerResult, pipe: LayerPipeline, frame, regions: list | None = None):
    """Sweep the twelve measures and :data:`THRESHOLDS` over the layer the step just analysed.

    ``res`` is :meth:`LayerPipeline.process`'s result for ``frame.photo`` (its
    considered blocks and printed area); the HOG blocks are those of the same
    top view (``pipe.last_top``) and reference. Returns ``(a (12, T), iou (12, T)
    or None, clean_high)``; fills ``regions`` with the (12, T) largest-region areas.
    """
    settings = pipe.config.analysis
    ref = pipe.reference(res.layer)
    top, valid, considered = pipe.last_top, pipe.last_valid, res.mask
    if top is None or considered is None:
        raise AnalysisError(f"layer {res.layer} was not analysed ({res.status}); nothing to sweep.")
    h_t, h_r = block_hogs(top, ref.image, settings)
    c, b = settings.cell_px, settings.block_cells
    sims = similarity_all(h_t, h_r, METRIC_NAMES)
    grow = float(settings.grow_threshold)
    n, m = considered.shape
    tile_px = float(c * c)
    tile_mm2 = (c / pipe.topview.px_per_mm) ** 2
    printed = res.printed_area_mm2
    T = THRESHOLDS
    a = np.zeros((len(METRIC_NAMES), len(T)), np.float32)
    iou = None
    truth_full = np.zeros((n, m))  # failed layers: tile area of the failed region per block, px
    truth_tiles, truth_px = truth_full[considered], 0.0
    reach = considered  # where a drawn region may grow (analyze_layer's grow_margin_mm)
    if frame.truth_area is not None:
        iou = np.zeros_like(a)
        truth_full = tile_fraction(frame.truth_area, n, m, c, b) * tile_px
        truth_tiles = truth_full[considered]
        truth_px = float(np.count_nonzero(frame.truth_area))
        if grow > 0:
            reach = growth_reach(considered, ref.footprint, pipe.topview, settings, valid)
    reg = np.zeros_like(a)
    # what each anomalous block adds to S_A (``[analysis] anomalous_area``): its tile, or its printed part
    weight = area_weight(tile_share(ref.footprint, (n, m), c, b), c / pipe.topview.px_per_mm,
                         settings.anomalous_area)[considered]
    for k, name in enumerate(METRIC_NAMES):
        if regions is not None:
            full = sims[name]
            for j, t in enumerate(T):
                reg[k, j] = _largest(considered & (full < t)) * tile_mm2
        s = sims[name][considered]
        below = s[:, None] < T[None, :]  # (blocks, T)
        cnt = weight @ below
        a[k] = anomaly_ratio(cnt, tile_mm2, printed)
        if iou is not None:
            if grow > 0:  # the regions the operator sees (hysteresis), as analyze_layer draws them
                full = sims[name]
                shown = np.stack([grow_regions(considered & (full < t), reach & (full < t + grow)).ravel()
                                  for t in T], axis=1)
                n_shown = shown.sum(axis=0)
                inter = (shown * truth_full.ravel()[:, None]).sum(axis=0)
            else:
                n_shown = below.sum(axis=0)
                inter = (below * truth_tiles[:, None]).sum(axis=0)
            union = n_shown * tile_px + truth_px - inter
            iou[k] = np.where(union > 0, inter / np.maximum(union, 1e-9), 1.0)
    clean_high = (0, 0, 0)
    if frame.truth_area is None:
        on_print = (tile_fraction(ref.footprint, n, m, c, b) >= 0.5) & considered
        cos = sims["cosine"]
        flat = np.logical_not(h_t.any(axis=2) | h_r.any(axis=2))  # featureless in both: similarity 1 by rule
        clean_high = (int(np.count_nonzero(cos[on_print] > 0.7)), int(np.count_nonzero(on_print)),
                      int(np.count_nonzero(flat[on_print])))
    if regions is not None:
        regions.append(reg)
    return a, iou, clean_high


def score_layer(pipe: LayerPipeline, frame, index: int) -> tuple[LayerResult, tuple | None]:
    """The evaluation's per-layer path: the monitor's step on ``frame.photo``, then the sweep.

    Returns
    -------
    result : LayerResult
        :meth:`LayerPipeline.process`'s record (the one the monitor stores for this photo).
    scores : (a, iou, clean_high, region) or None
        As :class:`LayerRecord` holds them; ``None`` when the photo could not
        be analysed (``result.status == "error"``, ``result.message`` says why).
    """
    res = pipe.process(frame.photo, index)
    if res.status == "error":
        return res, None
    regions: list = []
    a, iou, clean_high = _score(res, pipe, frame, regions)
    return res, (a, iou, clean_high, regions[0])


def run_evaluation(
    toolpath: Toolpath,
    config: JobConfig,
    camera: CameraModel,
    n_layers: int = 200,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
    match_camera: bool = False,
    beside_share: float = 0.0,
    modes: tuple[str, ...] = MODES,
    workers: int = 1,
    sim_settings: SimSettings | None = None,
) -> EvalData:
    """Simulate about ``n_layers`` layer photos and score them (see module notes).

    Parameters
    ----------
    toolpath : Toolpath
    config : JobConfig
        Top view, render and analysis settings (margin, HOG parameters).
    camera : CameraModel
        Posed camera of the simulated photos (also used by the pipeline).
    n_layers : int
        Approximate number of layer photos.
    seed : int
    progress : callable, optional
        ``progress(done, total)``.
    match_camera : bool
        Camera-matched references (see :class:`~layerwatch.pipeline.step.LayerPipeline`).
    beside_share : float
        Share of the foreign bodies and spaghetti placed on the bed beside the part.
    modes : tuple of str
        Modes scored per photo (:mod:`layerwatch.evaluate.modes`): ``"series"`` is the
        sweep's own pipeline; ``"single"`` runs each photo again through a second
        pipeline that forgets the print before every photo (bed photo only).
    workers : int
        Processes that score the scenarios (:func:`~layerwatch.evaluate.parallel.map_prints`;
        0 = every core). Each scenario has its own seed and pipelines, so the records are
        the same for any number.
    sim_settings : SimSettings, optional
        How the photos are made (default :class:`~layerwatch.simulate.settings.SimSettings`: the raster
        photographer; ``renderer = "blender"``: photoreal, :mod:`layerwatch.simulate.photoreal`).

    Returns
    -------
    EvalData
    """
    t0 = time.perf_counter()
    config = config.for_camera(camera)  # truth masks in the pipeline's top view
    plan = plan_frames(toolpath, n_layers, seed=seed, beside_share=beside_share)
    total = sum(len(ls) for _, ls in plan)
    data = EvalData(setup={
        "n_frames": total, "n_scenarios": len(plan), "image_size": list(camera.image_size),
        "analysis": config.analysis.model_dump(), "match_camera": match_camera, "scene": config.scene.enabled, "beside_share": beside_share,
        "toolpath": Path(str(toolpath.source)).name, "toolpath_layers": toolpath.n_layers, "seed": seed,
        "thin_walls": has_thin_walls(toolpath),  # else a thin-wall defect is a wall gap (report row label)
        "renderer": _renderer(sim_settings),
    })
    planned = {sc.failures[0].type for sc, _ in plan if sc.failures}
    for t in FAILURE_TYPES:
        if t not in planned:
            data.errors.append(f"{t}: not injected, no layer of this part can take it (e.g. no infill or no "
                               "perimeters marked in the G-code); not scored")
    data.setup["modes"] = list(modes)
    tasks = [(toolpath, camera, config, scen, layers, seed * 1000 + k, match_camera, modes, sim_settings)
             for k, (scen, layers) in enumerate(plan)]
    for records, errors in map_prints(_scenario_records, tasks, [len(ls) for _, ls in plan], workers, progress):
        data.records += records
        data.errors += errors
    data.seconds = time.perf_counter() - t0
    return data


def _renderer(settings: SimSettings | None) -> str:
    """How the photos were made, for the report: ``"raster"`` or ``"blender (N samples)"``."""
    if settings is None or settings.renderer == "raster":
        return "raster"
    return f"blender ({settings.blender_samples} samples)"


def _scenario_records(toolpath: Toolpath, camera: CameraModel, config: JobConfig, scen: Scenario, layers: list[int],
                      sim_seed: int, match_camera: bool, modes: tuple[str, ...], sim_settings: SimSettings | None,
                      tick: Callable[[], None]) -> tuple[list[LayerRecord], list[str]]:
    """Simulate one scenario's photos and score them (one task of :func:`run_evaluation`).

    Each scenario runs in a pipeline of its own (series mode: the print's own history;
    single mode: a second pipeline that forgets the print before every photo), so a
    scenario scores the same whichever worker runs it.
    """
    tv = config.topview.topview()
    pipe = LayerPipeline(toolpath, camera, config, match_camera=match_camera, memo=toolpath.n_layers)
    single = (LayerPipeline(toolpath, camera, config, match_camera=match_camera, memo=toolpath.n_layers)
              if "single" in modes else None)
    sim = PrintSimulator(toolpath, camera, tv, scen, seed=sim_seed, settings=sim_settings)
    bed = sim.bed_photo()
    pipe.new_print(bed if pipe.scene is not None else None)
    size = scen.failures[0].size_mm if scen.failures else 0.0
    moved = sim.failures[0].offset if scen.failures and scen.failures[0].type in ("layer_shift", "detachment") else None
    records: list[LayerRecord] = []
    errors: list[str] = []
    patch = patch_layers(sim.failures[0], toolpath) if sim.failures else []
    for i in layers:
        frame = sim.frame(i)
        res, scores = score_layer(pipe, frame, i)
        tick()
        if scores is None:  # reported, the run continues
            errors.append(f"{scen.name} layer {i}: {res.message}")
            continue
        by_mode = {"series": mode_score(res, frame.truth_area, tv, moved)} if "series" in modes else {}
        if single is not None:  # the same photo with nothing of the print before it
            single.new_print(bed if single.scene is not None else None)
            by_mode["single"] = mode_score(single.process(frame.photo, i), frame.truth_area, tv, moved)
        a, iou, clean_high, region = scores
        kind = frame.meta["failures"][0] if frame.meta.get("failures") else "clean"
        since = int(i) - scen.failures[0].onset if kind != "clean" else -1
        if i in patch:  # a patch's layers: those it removed beads on since its onset
            since = patch.index(i)
        surface = surface_under(toolpath, i, frame.truth_area, tv) if frame.truth_area is not None else ""
        records.append(LayerRecord(scen.name, kind, int(i), float(size if kind != "clean" else 0.0),
                                   a, iou, clean_high, region, since, surface,
                                   float(res.outside_anomalous_mm2), float(res.printed_area_mm2), by_mode))
    return records, errors


#: the counts of :func:`clean_false_alarms`, per part and in all
_CLEAN_COUNTS = ("layers", "prints", "layer_alarms", "ratio_layers", "policy_alarms", "pauses", "outside_layers")


def _clean_print(toolpath: Toolpath, config: JobConfig, camera: CameraModel, policy_settings, sim_seed: int,
                 sim_settings: SimSettings | None, tick: Callable[[], None]) -> dict:
    """Run one whole clean print of ``toolpath`` through the step and the policy; the counts of :func:`clean_false_alarms`."""
    tv = config.topview.topview()
    pipe = LayerPipeline(toolpath, camera, config, memo=toolpath.n_layers)
    out: dict[str, Any] = {k: 0 for k in _CLEAN_COUNTS} | {"prints": 1, "max_a": 0.0, "a": [], "max_outside_mm2": 0.0}
    sim = PrintSimulator(toolpath, camera, tv, (), seed=sim_seed, settings=sim_settings)
    pipe.new_print(sim.bed_photo() if pipe.scene is not None else None)
    paused = False
    photos = ((i, sim.frame(i).photo) for i in range(toolpath.n_layers))
    for res, decision in judge_layers(pipe, PausePolicy(policy_settings), photos):
        tick()
        if res.status != "ok":
            continue
        out["layers"] += 1
        out["a"].append(float(res.anomaly_ratio))
        out["max_a"] = max(out["max_a"], float(res.anomaly_ratio))
        out["outside_layers"] += int(res.outside_anomalous_mm2 > 0)
        out["max_outside_mm2"] = max(out["max_outside_mm2"], float(res.outside_anomalous_mm2))
        if res.layer >= policy_settings.skip_first_layers:
            # a single-layer alarm is the policy's own ratio test (a% and anomalous area, :func:`layer_alarm`);
            # a% alone above the ratio is kept beside it (on a small footprint one block is several %)
            out["layer_alarms"] += int(layer_alarm(float(res.anomaly_ratio),
                                                   float(res.anomalous_area_mm2) + float(res.uncounted_mm2),
                                                   policy_settings))
            out["ratio_layers"] += int(res.anomaly_ratio > policy_settings.pause_ratio)
        if not paused:  # after a pause the policy waits for the operator: nothing more to count
            out["policy_alarms"] += int(decision.action != "none")
        if decision.stops and not paused:
            out["pauses"] += 1
            paused = True
    return out


def _add_counts(into: dict, got: dict) -> None:
    """Add one print's (or part's) counts of :func:`clean_false_alarms` to ``into``."""
    for key in _CLEAN_COUNTS:
        into[key] += got[key]
    into["a"] += got["a"]
    into["max_a"] = max(into["max_a"], got["max_a"])
    into["max_outside_mm2"] = max(into["max_outside_mm2"], got["max_outside_mm2"])


def clean_false_alarms(
    toolpath: Toolpath,
    config: JobConfig,
    camera: CameraModel,
    n_layers: int,
    pause_ratio: float,
    consecutive: int = 2,
    seed: int = 100,
    progress: Callable[[int, int], None] | None = None,
    window_share: float = 0.25,
    workers: int = 1,
    sim_settings: SimSettings | None = None,
) -> dict:
    """Simulate whole clean prints (about ``n_layers`` photos) and count false alarms.

    Uses ``config.analysis`` as is (measure, T_S, margin). A *layer* alarm is
    the policy's ratio test on one layer (:func:`~layerwatch.pipeline.policy.layer_alarm`:
    a% > ``pause_ratio`` with at least ``config.policy.min_area_mm2`` of anomalous
    area; ``ratio_layers`` counts a% > ``pause_ratio`` alone); a *pause* is what the monitor's own
    :class:`~layerwatch.pipeline.policy.PausePolicy` decides with
    ``config.policy`` and that pause ratio and ``consecutive`` layers (a%
    above the ratio on consecutive layers with overlapping regions, or a
    strong event of material outside the part), counted once per print.
    Prints run in series mode (one pipeline per print, as the monitor does).

    ``window_share`` of the layers are prints of the simulator's
    :func:`~layerwatch.simulate.parts.window_part` (a hollow box with a window
    through its wall, a bridge and an overhang: what a height-map reference
    cannot hold), centred on the observed square; the rest are prints of ``toolpath``.
    Each print has its own seed and pipeline, so ``workers`` processes (0 = every core)
    give the same counts as one. ``sim_settings``: how the photos are made (as :func:`run_evaluation`).

    Returns
    -------
    dict
        ``layers``, ``prints``, ``layer_alarms`` (the policy's ratio test), ``ratio_layers`` (a% above
        the ratio, whatever the area), ``policy_alarms``
        (the policy's notify/pause decisions on analysed layers), ``pauses``, ``max_a``, ``a`` (list),
        ``outside_layers`` (layers with any scene-channel change beside the print), ``max_outside_mm2``,
        and ``parts``: the same counts per part (``{name: {...}}``, without ``a``).
    """
    config = config.for_camera(camera)  # the pipeline's top view
    policy_settings = config.policy.model_copy(update={"pause_ratio": float(pause_ratio),
                                                       "consecutive_layers": int(consecutive)})
    share = min(max(float(window_share), 0.0), 1.0)
    parts = [(Path(str(toolpath.source)).name or "part", toolpath, n_layers * (1.0 - share))]
    if share > 0:
        parts.append(("window part", window_part(center=(float(config.topview.center_mm[0]), float(config.topview.center_mm[1]))), n_layers * share))
    plan = [(name, tp, max(1, int(round(n / tp.n_layers)))) for name, tp, n in parts if n > 0]
    tasks = [(tp, config, camera, policy_settings, seed + 1000 * k + j, sim_settings)
             for k, (_, tp, prints) in enumerate(plan) for j in range(prints)]
    names = [name for name, _, prints in plan for _ in range(prints)]
    out: dict[str, Any] = {k: 0 for k in _CLEAN_COUNTS} | {"max_a": 0.0, "a": [], "max_outside_mm2": 0.0, "parts": {}}
    blank = {k: 0 for k in _CLEAN_COUNTS} | {"max_a": 0.0, "a": [], "max_outside_mm2": 0.0}
    results = map_prints(_clean_print, tasks, [t[0].n_layers for t in tasks], workers, progress)
    for name, got in zip(names, results, strict=True):
        _add_counts(out, got)
        _add_counts(out["parts"].setdefault(name, {**blank, "a": []}), got)
    for part in out["parts"].values():
        part.pop("a")
    return out
