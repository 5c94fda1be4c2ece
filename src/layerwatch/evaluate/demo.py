"""The end-to-end demo: a simulated print with a failure, analysed as a printer would.

prepare (snapshot G-code) -> render (references) -> simulate camera ->
locate the bed (pose from the markers in the first photo) -> warp ->
analyse -> decide; stops at the layer where a real printer would have been
paused. Everything is written to a results folder
(:class:`~layerwatch.evaluate.results.ResultsFolder`) and the job to the
history database ``history.db`` the monitor writes (``layerwatch demo`` then
builds its HTML report). The per-layer step and the pause decision are the
pipeline's (:func:`~layerwatch.pipeline.step.judge_layers`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from layerwatch.evaluate.results import ResultsFolder
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.geometry.pose import locate_bed
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline, judge_layers
from layerwatch.simulate import Failure, PrintSimulator, default_camera
from layerwatch.storage import History

__all__ = ["DemoResult", "run_demo"]


@dataclass
class DemoResult:
    """What the demo did: ``paused_at`` (layer or None), ``onset``, per-layer a%, paths."""

    out: Path
    paused_at: int | None
    onset: int
    failure: str
    reason: str = ""
    anomaly: dict[int, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0
    policy: str = "pipeline.policy.PausePolicy"
    job_id: int | None = None
    report: Path | None = None


def run_demo(
    out: str | Path,
    *,
    layers: int | None = None,
    failure: str = "spaghetti",
    onset: int = 15,
    size_mm: float = 18.0,
    seed: int = 1,
    image_size: tuple[int, int] = (1280, 720),
    place: str | None = None,
    stop_at_pause: bool = True,
    progress: Callable[[int, int, str], None] | None = None,
) -> DemoResult:
    """Run the demo into ``out``.

    Parameters
    ----------
    out : str or Path
        Results folder.
    layers : int, optional
        Simulate only the first ``layers`` layers.
    failure, onset, size_mm, seed
        Injected failure (type, first layer, size) and the simulation seed.
    place : {"on", "beside"}, optional
        Where a spaghetti or foreign body lands (default: beside the part, on
        the bed, where only the scene channel sees it; other types: on the part).
    image_size : (int, int)
        Camera resolution.
    stop_at_pause : bool
        Stop at the layer where the pause decision is taken.
    progress : callable, optional
        ``progress(done, total, text)`` after each layer.

    Returns
    -------
    DemoResult
    """
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    notes: list[str] = []
    gpath = PART_GCODE
    tp = read_toolpath(gpath)
    cfg = resolve_config(PART_CONFIG).config
    tv = cfg.topview.topview()
    # prepare: the G-code a printer would run (snapshot block after every layer)
    (out / "prepared.gcode").write_bytes(insert_snapshots(gpath.read_bytes(), cfg.snapshot, cfg.printer))
    n = tp.n_layers if layers is None else max(1, min(int(layers), tp.n_layers))
    onset = min(int(onset), n - 1)
    truth_cam = default_camera(tv, image_size=image_size)
    if place is None:
        place = "beside" if failure in ("spaghetti", "foreign_body") else "on"
    sim = PrintSimulator(tp, truth_cam, tv, [Failure(failure, onset=onset, size_mm=size_mm, seed=seed, place=place)],
                         seed=seed)
    # calibrate the pose from the markers in the first photo, as a user would
    first = sim.frame(0)
    camera = locate_bed(dataclasses.replace(truth_cam, rvec=None, tvec=None), first.photo, cfg.markers, tv)
    notes.append(f"camera pose from the bed markers: reprojection error {camera.errors.get('pose_px', float('nan')):.2f} px")
    folder = ResultsFolder(out, tv)
    res_demo = DemoResult(out, None, onset, failure if place == "on" else f"{failure} beside the part", notes=notes)
    # the empty bed, photographed before the print as `calibrate --markers` keeps it: the scene's baseline
    pipe = LayerPipeline(tp, camera, cfg, bed_photo=sim.bed_photo())
    results = _watch(pipe, PausePolicy(cfg.policy), sim, first, n, folder, res_demo,
                     stop_at_pause, progress)
    folder.stack()
    _record_history(out, gpath, results, res_demo, cfg)
    res_demo.seconds = time.perf_counter() - t0
    folder.summary(results, res_demo.paused_at, res_demo.reason, extra={
        "part": str(gpath), "injected failure": f"{failure} from layer {onset} ({place} the part)",
        "policy": res_demo.policy, "seconds": round(res_demo.seconds, 1),
        "analysis": cfg.analysis.model_dump(), "pause_rule": cfg.policy.model_dump(),
    })
    return res_demo


def _watch(pipe: LayerPipeline, policy: PausePolicy, sim: PrintSimulator, first, n: int, folder: ResultsFolder,
           res_demo: DemoResult, stop_at_pause: bool, progress) -> dict:
    """The simulated photos of layers ``0..n-1`` through :func:`judge_layers`, written to ``folder``; results by layer."""
    results = {}
    failures: dict[int, list[str]] = {}

    def photos():
        for i in range(n):
            frame = first if i == 0 else sim.frame(i)
            failures[i] = list(frame.meta.get("failures", []))
            yield i, frame.photo

    for res, decision in judge_layers(pipe, policy, photos()):
        i = res.layer
        res.simulated_failures = failures[i]
        ref = pipe.reference(i) if res.status != "error" else None
        folder.write(res, pipe.last_top, None if ref is None else ref.footprint, None if ref is None else ref.image)
        results[i] = res
        res_demo.anomaly[i] = float(res.anomaly_ratio) if res.status == "ok" else float("nan")
        if progress is not None:
            progress(i + 1, n, f"layer {i}: a% {100 * res.anomaly_ratio:.0f}")
        if decision.stops and res_demo.paused_at is None:
            res_demo.paused_at, res_demo.reason = i, decision.reason
            if stop_at_pause:
                break
    return results


def _record_history(out: Path, gpath: Path, results: dict, res_demo: DemoResult, cfg=None) -> None:
    """Store the demo job in ``out/history.db`` (``res_demo.job_id``).

    The same history the live monitor writes, so ``layerwatch history --db
    out/history.db`` and ``layerwatch report`` work on the demo job.
    """
    if results and (out / "stack.png").is_file():
        results[max(results)].images["stack"] = "stack.png"
    with History(out / "history.db") as history:
        job = history.start_job("virtual", gcode_path=str(gpath), part="demo part", config=cfg)
        for res in results.values():
            history.add_layer(job, res)
        if res_demo.paused_at is not None:
            history.add_event(job, "pause", f"paused at layer {res_demo.paused_at}: {res_demo.reason}")
        history.end_job(job, "paused" if res_demo.paused_at is not None else "finished")
    res_demo.job_id = job
