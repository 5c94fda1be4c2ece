"""The end-to-end demo: a simulated print with a failure, analysed as a printer would.

prepare (snapshot G-code) -> render (references) -> simulate camera ->
locate the bed (pose from the markers in the first photo) -> warp ->
analyse -> decide; stops at the layer where a real printer would have been
paused. Everything is written to a results folder
(:class:`~layerwatch.evaluate.results.ResultsFolder`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["DemoResult", "load_job_toolpath", "run_demo"]


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
    policy: str = ""
    report: Path | None = None


def load_job_toolpath(gcode: str | Path | None, notes: list[str] | None = None):
    """Parse ``gcode`` (default: the bundled example) with read_toolpath; box_part() if the parser is missing."""
    from layerwatch.examples import PART_GCODE

    notes = notes if notes is not None else []
    path = Path(gcode) if gcode is not None else PART_GCODE
    try:
        from layerwatch.gcode import read_toolpath
    except ImportError:
        read_toolpath = None
    if read_toolpath is None:
        from layerwatch.simulate.parts import box_part

        notes.append("G-code parser (layerwatch.gcode.read_toolpath) missing: using the synthetic box_part() instead")
        return box_part(center=(110.0, 100.0)), None
    return read_toolpath(path), path


def run_demo(
    out: str | Path,
    *,
    layers: int | None = None,
    failure: str = "spaghetti",
    onset: int = 15,
    size_mm: float = 18.0,
    seed: int = 1,
    image_size: tuple[int, int] = (1280, 720),
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
    from layerwatch.evaluate.decision import decision_action, pause_policy
    from layerwatch.evaluate.recommended import recommended_config
    from layerwatch.evaluate.results import ResultsFolder
    from layerwatch.examples import PART_CONFIG
    from layerwatch.geometry.pose import locate_bed
    from layerwatch.monitor.pipeline import LayerPipeline
    from layerwatch.simulate import Failure, PrintSimulator, default_camera

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    notes: list[str] = []
    tp, gpath = load_job_toolpath(None, notes)
    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    # prepare: the G-code a printer would run (snapshot block after every layer)
    if gpath is not None:
        try:
            from layerwatch.gcode.postprocess import insert_snapshots
        except ImportError:
            notes.append("gcode.postprocess.insert_snapshots missing: prepared G-code not written")
        else:
            (out / "prepared.gcode").write_bytes(insert_snapshots(gpath.read_bytes(), cfg.snapshot, cfg.printer))
    n = tp.n_layers if layers is None else max(1, min(int(layers), tp.n_layers))
    onset = min(int(onset), n - 1)
    truth_cam = default_camera(tv, image_size=image_size)
    sim = PrintSimulator(tp, truth_cam, tv, [Failure(failure, onset=onset, size_mm=size_mm, seed=seed)], seed=seed)
    # calibrate the pose from the markers in the first photo, as a user would
    first = sim.frame(0)
    camera = locate_bed(dataclasses.replace(truth_cam, rvec=None, tvec=None), first.photo, cfg.markers, tv)
    notes.append(f"camera pose from the bed markers: reprojection error {camera.errors.get('pose_px', float('nan')):.2f} px")
    pipe = LayerPipeline(tp, camera, cfg)
    policy = pause_policy(cfg.policy)
    folder = ResultsFolder(out, tv)
    results = {}
    res_demo = DemoResult(out, None, onset, failure, notes=notes, policy=getattr(policy, "source", type(policy).__name__))
    for i in range(n):
        frame = first if i == 0 else sim.frame(i)
        res = pipe.process(frame.photo, i)
        res.extra["simulated_failures"] = frame.meta.get("failures", [])
        ref = pipe.reference(i) if res.status != "error" else None
        folder.write(res, pipe.last_top, None if ref is None else ref.footprint,
                             None if ref is None else ref.image)
        results[i] = res
        res_demo.anomaly[i] = float(res.anomaly_ratio) if res.status == "ok" else float("nan")
        decision = policy.update(res)
        action = decision_action(decision)
        if progress is not None:
            progress(i + 1, n, f"layer {i}: a% {100 * res.anomaly_ratio:.0f}")
        if action in ("pause", "cancel") and res_demo.paused_at is None:
            res_demo.paused_at, res_demo.reason = i, str(getattr(decision, "reason", ""))
            if stop_at_pause:
                break
    folder.stack()
    _record_history(out, gpath, results, res_demo, cfg)
    res_demo.seconds = time.perf_counter() - t0
    folder.summary(results, res_demo.paused_at, res_demo.reason, extra={
        "part": str(gpath) if gpath else "box_part()", "injected failure": f"{failure} from layer {onset}",
        "policy": res_demo.policy, "seconds": round(res_demo.seconds, 1),
        "analysis": cfg.analysis.model_dump(), "pause_rule": cfg.policy.model_dump(),
    })
    return res_demo



def _record_history(out: Path, gpath: Path | None, results: dict, res_demo: DemoResult, cfg=None) -> None:
    """Store the demo job in ``out/history.db`` and write its HTML report to ``out/report/``.

    The same history the live monitor writes, so ``layerwatch history --db
    out/history.db`` and ``layerwatch report`` work on the demo job.
    """
    from layerwatch.storage import History
    from layerwatch.web.report import build_report

    if results and (out / "stack.png").is_file():
        results[max(results)].images["stack"] = "stack.png"
    history = History(out / "history.db")
    try:
        job = history.start_job("virtual", gcode_path=str(gpath) if gpath else None, part="demo part", config=cfg)
        for res in results.values():
            history.add_layer(job, res)
        if res_demo.paused_at is not None:
            history.add_event(job, "pause", f"paused at layer {res_demo.paused_at}: {res_demo.reason}")
        history.end_job(job, "paused" if res_demo.paused_at is not None else "finished")
        res_demo.report = build_report(history, job, out / "report", image_root=out)
    finally:
        close = getattr(history, "close", None)
        if close is not None:
            close()
