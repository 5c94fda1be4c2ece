"""The plate demo: one of four objects fails, is cancelled alone, and the other three finish.

``layerwatch demo --plate`` prints :func:`~layerwatch.simulate.plate.plate_gcode`
(four copies of the bundled part, labelled for Klipper's ``EXCLUDE_OBJECT``)
on the simulator with a failure on one object, through the real pipeline, pause
policy and :class:`~layerwatch.pipeline.actions.ActionExecutor` on a simulated
Klipper host (:class:`SimulatedKlipper`: it records the lines it is sent). The job file is the bundled part's with every failure kind set to
``cancel_object`` (region typing may leave a region untyped, ``"unknown"``):
the policy's stop becomes ``EXCLUDE_OBJECT NAME=<object>``; from the next layer
the simulator no longer prints that object, the reference and footprint leave
it out, and the policy no longer judges its area, so the print runs to the end.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from layerwatch.analysis.failure_kinds import FAILURE_KINDS
from layerwatch.evaluate.results import ResultsFolder
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.objects import PrintObject, read_objects, without_objects
from layerwatch.geometry.pose import locate_bed
from layerwatch.pipeline.actions import ActionExecutor
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera
from layerwatch.simulate.plate import plate_gcode

__all__ = ["PLATE_FAILURES", "PlateDemoResult", "SimulatedKlipper", "run_plate_demo"]

#: failures the simulator puts on a given point (the failing object's centre)
PLATE_FAILURES = ("spaghetti", "foreign_body")


class SimulatedKlipper:
    """The host of the simulated print: keeps its state and the lines the executor sends it."""

    def __init__(self) -> None:
        self.state = "printing"
        self.sent: list[str] = []

    def pause(self) -> None:
        self.state = "paused"

    def cancel(self) -> None:
        self.state = "cancelled"

    def send_gcode(self, lines: str | list[str]) -> None:
        self.sent += [lines] if isinstance(lines, str) else list(lines)

    def cancel_object(self, obj: PrintObject) -> None:
        self.send_gcode(f"EXCLUDE_OBJECT NAME={obj.klipper_name}")

    def show_message(self, text: str) -> None:
        self.send_gcode([f"M117 {text}", f'RESPOND TYPE=echo MSG="{text}"'])


@dataclass
class PlateDemoResult:
    """What the plate demo did.

    Attributes
    ----------
    out : Path
    objects : list of str
        The plate's object names.
    failed : str
        The object the failure was put on.
    cancelled : dict of str to int
        Object name -> layer after which it was cancelled.
    stops : list of (int, str, str)
        Every stopping decision as carried out: (layer, action, reason).
    layers : int
        Layers simulated; the print ran to the end when it equals the plate's layer count.
    later_alarms : list of (int, str, str, bool)
        Notifications after the cancel: (layer, action, reason, about a cancelled object).
    host_lines : list of str
        What the host was sent (``EXCLUDE_OBJECT NAME=..``, the ``M117`` / ``RESPOND`` message).
    """

    out: Path
    objects: list[str]
    failed: str
    failure: str
    onset: int
    cancelled: dict[str, int] = field(default_factory=dict)
    stops: list[tuple[int, str, str]] = field(default_factory=list)
    layers: int = 0
    total_layers: int = 0
    later_alarms: list[tuple[int, str, str, bool]] = field(default_factory=list)
    host_lines: list[str] = field(default_factory=list)
    seconds: float = 0.0


def run_plate_demo(out: str | Path, *, failed: int = 1, failure: str = "spaghetti", onset: int = 12,
                   size_mm: float = 8.0, seed: int = 1, image_size: tuple[int, int] = (1280, 720),
                   progress: Callable[[int, int, str], None] | None = None) -> PlateDemoResult:
    """Run the plate demo into ``out`` (overlays, ``plate.gcode``, ``summary.md``).

    Parameters
    ----------
    failed : int
        Index of the object the failure lands on (0..3).
    failure, onset, size_mm, seed
        The injected failure (a type the simulator places on a point: ``spaghetti``,
        ``foreign_body``), its first layer, size and the seed.
    """
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = plate_gcode(read_toolpath(PART_GCODE))
    (out / "plate.gcode").write_bytes(data)
    tp = read_toolpath(data)
    objects = read_objects(data, tp)
    target = objects.objects[failed]
    kinds = {k: {"action": "cancel_object"} for k in FAILURE_KINDS}
    cfg = resolve_config(PART_CONFIG, flags={"policy": {"kinds": kinds}}).config
    tv = cfg.topview.topview()
    truth = default_camera(tv, image_size=image_size)
    sim = PrintSimulator(tp, truth, tv, [Failure(failure, onset=onset, size_mm=size_mm, seed=seed,
                                                 center_mm=target.center_mm)], seed=seed)
    first = sim.frame(0)
    camera = locate_bed(dataclasses.replace(truth, rvec=None, tvec=None), first.photo, cfg.markers, tv)
    pipe = LayerPipeline(tp, camera, cfg, bed_photo=sim.bed_photo())
    policy = PausePolicy(cfg.policy)
    printer = SimulatedKlipper()
    actions = ActionExecutor(printer, objects, pipe)
    folder = ResultsFolder(out, tv)
    result = PlateDemoResult(out, [o.name for o in objects.objects], target.name, failure, onset,
                             total_layers=tp.n_layers)
    results = {}
    for i in range(tp.n_layers):
        photo = first.photo if i == 0 else sim.frame(i).photo
        res = pipe.process(photo, i)
        decision = policy.update(res)
        if decision.stops:
            done = actions.execute(decision, policy)
            decision = done.decision
            result.stops.append((i, decision.action, decision.reason))
            if done.target is not None:
                result.cancelled[done.target.name] = i
                sim.tp = without_objects(tp, objects, actions.cancelled)  # the printer skips it from now on
        elif decision.action != "none" and result.cancelled:
            gone = [objects.objects[k].bbox_mm for k in actions.cancelled]
            about = any(b[0] <= r.centroid_mm[0] <= b[2] and b[1] <= r.centroid_mm[1] <= b[3]
                        for r in decision.regions for b in gone)
            result.later_alarms.append((i, decision.action, decision.reason, about))
        res.decision, res.decision_reason = decision.action, decision.reason
        ref = pipe.reference(i) if res.status != "error" else None
        folder.write(res, pipe.last_top, None if ref is None else ref.footprint, None if ref is None else ref.image)
        results[i] = res
        result.layers = i + 1
        if progress is not None:
            progress(i + 1, tp.n_layers, f"layer {i}: a% {100 * res.anomaly_ratio:.0f}")
        if printer.state != "printing":  # paused (no object to cancel alone): a person must look
            break
    folder.stack()
    result.host_lines = list(printer.sent)
    result.seconds = time.perf_counter() - t0
    folder.summary(results, None, "", extra={
        "plate": "plate.gcode (four copies of the bundled part)", "injected failure":
        f"{failure} on {target.name} from layer {onset}", "cancelled": result.cancelled,
        "stops": [f"layer {n}: {a}: {r}" for n, a, r in result.stops], "layers printed": result.layers,
        "seconds": round(result.seconds, 1)})
    return result
