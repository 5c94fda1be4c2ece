"""Object cancel from detected regions: failures on every object of the labelled multi-object plates.

For each labelled multi-object G-code file (:func:`find_plates`: every file of a folder whose
labels name at least two objects) and each of its objects, :func:`plate_cases` places failures
on that object (a foreign body or spaghetti on one of its printed points, an infill or thin-wall
gap on its infill or walls, the object alone coming off the bed: ``Failure.within_mm``) at a
few onsets. :func:`run_case` simulates the plate's photos with that failure
(:class:`~layerwatch.simulate.PrintSimulator`), judges every layer with the recommended
per-layer pipeline and pause policy (every failure kind's action set to ``cancel_object``, as
in ``layerwatch demo --plate``: region typing may call a region another kind), and at the
first stopping decision carries it out with the real
:class:`~layerwatch.pipeline.actions.ActionExecutor` on a recording host: the decision's
regions are mapped to objects by :meth:`~layerwatch.gcode.objects.ObjectMap.locate`.

Outcomes: ``correct`` (the failed object alone was cancelled), ``wrong`` (another object was
cancelled: the count that must be 0), ``pause`` (no single object: the regions span objects,
touch none; the reason says which), ``early`` (a stop before the failure's onset: a false
alarm, whatever it cancelled), ``missed`` (no stop within ``max_after`` layers of the onset).
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from layerwatch.analysis.failure_kinds import FAILURE_KINDS
from layerwatch.analysis.result import LayerResult
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.objects import (
    ObjectMap,
    PrintObject,
    quiet_layers,
    read_objects,
    without_objects,
)
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.pose import locate_bed
from layerwatch.pipeline.actions import ActionExecutor
from layerwatch.pipeline.config import observed_square, resolve_config
from layerwatch.pipeline.policy import Decision, PausePolicy
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera
from layerwatch.simulate.failures import selectable

__all__ = ["CANCEL_KINDS", "CancelCase", "CaseResult", "find_plates", "iter_cases", "plate_cases", "run_case", "run_cases",
           "summary_table", "tally"]

#: failure kinds placed on one object, with their size range (mm: diameter; detachment: the move)
CANCEL_KINDS: dict[str, tuple[float, float]] = {
    "foreign_body": (4.0, 7.0),
    "spaghetti": (6.0, 10.0),
    "infill_defect": (3.0, 5.0),
    "thin_wall": (3.0, 5.0),
    "detachment": (1.5, 3.0),
}
#: onsets as fractions of the object's printed layers
ONSET_FRACTIONS = (0.3, 0.6)


@dataclass(frozen=True)
class CancelCase:
    """One simulated print: ``failure`` on object ``target`` of plate ``plate`` (a file name)."""

    plate: str
    target: int
    failure: Failure

    @property
    def label(self) -> str:
        f = self.failure
        return f"{self.plate}: {f.type} on object {self.target} from layer {f.onset} ({f.size_mm:.1f} mm)"


@dataclass
class CaseResult:
    """What the pipeline and the executor did for one :class:`CancelCase`.

    Attributes
    ----------
    outcome : str
        ``"correct"``, ``"wrong"``, ``"pause"``, ``"early"`` or ``"missed"`` (module notes).
    layer : int
        Layer of the stopping decision (-1: none).
    kind : str
        The decision's failure kind (the typing's, not the injected one).
    cancelled : str
        Name of the object cancelled ("" none).
    reason : str
        The decision's reason as carried out (a fallback says why no object was cancelled).
    located : tuple of int
        The objects the decision's regions touch (most touched first).
    layers : int
        Layers simulated.
    later : list of (int, str, str)
        With ``follow``: every decision other than ``"none"`` on the layers after a cancel, as
        ``(layer, action, reason)`` (the first stopping one ends the list).
    seconds : float
    """

    case: CancelCase
    target_name: str
    outcome: str = "missed"
    layer: int = -1
    kind: str = ""
    cancelled: str = ""
    reason: str = ""
    located: tuple[int, ...] = ()
    layers: int = 0
    later: list[tuple[int, str, str]] = dataclasses.field(default_factory=list)
    seconds: float = 0.0


class _RecordingHost:
    """A printer host that accepts every action and keeps what it was asked to do."""

    def __init__(self) -> None:
        self.sent: list[str] = []

    def pause(self) -> None:
        self.sent.append("pause")

    def cancel(self) -> None:
        self.sent.append("cancel")

    def send_gcode(self, lines: str | list[str]) -> None:
        self.sent += [lines] if isinstance(lines, str) else list(lines)

    def cancel_object(self, obj: PrintObject) -> None:
        self.sent.append(f"cancel object {obj.name}")


def find_plates(folder: str | Path, names: Iterable[str] | None = None) -> dict[str, tuple[Toolpath, ObjectMap]]:
    """The labelled multi-object G-code files of ``folder``: file name -> (toolpath, objects).

    Parameters
    ----------
    folder : str or Path
        Folder of G-code files (``*.gcode``, ``*.g``, ``*.bgcode``).
    names : iterable of str, optional
        Read only these file names (default: every file; those whose labels name fewer than two
        objects, or that do not read, are left out).
    """
    out: dict[str, tuple[Toolpath, ObjectMap]] = {}
    folder = Path(folder)
    paths = [folder / n for n in names] if names is not None else sorted(
        p for p in folder.iterdir() if p.suffix.lower() in (".gcode", ".g", ".bgcode"))
    for path in paths:
        try:
            tp = read_toolpath(path)
            om = read_objects(path, tp)
        except Exception:  # noqa: BLE001 - a file that does not read is no plate to evaluate
            continue
        if om.labelled:
            out[path.name] = (tp, om)
    return out


def _object_layers(tp: Toolpath, om: ObjectMap, index: int) -> list[int]:
    return [lay.index for lay in tp.layers
            if (om.segment_object[lay.seg_start:lay.seg_stop] == index).any()]


def _point(tp: Toolpath, om: ObjectMap, obj: int, layer: int, kind: str, rng: np.random.Generator):
    """A midpoint of one of ``obj``'s segments on ``layer`` that ``kind`` can remove (None: none there).

    As the simulator selects them (:func:`~layerwatch.simulate.failures.selectable`).
    """
    sl = tp.layer_slice(layer)
    mine = om.segment_object[sl] == obj
    if kind in ("infill_defect", "thin_wall"):
        mine &= selectable(tp, layer, kind)
    idx = np.flatnonzero(mine)
    if not len(idx):
        return None
    k = int(rng.choice(idx)) + sl.start
    return tuple(float(v) for v in (tp.start[k] + tp.end[k]) / 2)


def plate_cases(name: str, tp: Toolpath, om: ObjectMap, *, kinds: Sequence[str] = tuple(CANCEL_KINDS),
                onsets: Sequence[float] = ONSET_FRACTIONS, seed: int = 0) -> tuple[list[CancelCase], list[str]]:
    """Failures on every object of one plate: each kind at each onset fraction of the object's layers.

    Onsets lie between the second judged layer and the object's last layer but one (two layers in a
    row decide). A kind that finds nothing of its own on the object at the onset (no infill, no
    wall) is left out for that object, with a note.

    Returns
    -------
    cases : list of CancelCase
    notes : list of str
        What was left out and why.
    """
    rng = np.random.default_rng([seed, sum(name.encode())])
    cases: list[CancelCase] = []
    notes: list[str] = []
    for obj in om.objects:
        layers = [i for i in _object_layers(tp, om, obj.index) if i >= 2]
        if len(layers) < 3:
            notes.append(f"{name}: {obj.name} has {len(layers)} layers after the first two: nothing to judge")
            continue
        for kind in kinds:
            lo, hi = CANCEL_KINDS[kind]
            for q in onsets:
                onset = layers[min(int(q * (len(layers) - 1)), len(layers) - 3)]
                size = float(rng.uniform(lo, hi))
                fseed = int(rng.integers(2**31))
                if kind == "detachment":
                    x0, y0, x1, y1 = obj.bbox_mm
                    f = Failure(kind, onset, size, fseed, within_mm=(x0 - 0.5, y0 - 0.5, x1 + 0.5, y1 + 0.5))
                else:
                    at = _point(tp, om, obj.index, onset, kind, rng)
                    if at is None:
                        notes.append(f"{name}: {obj.name} prints no {kind.replace('_defect', '')} on layer {onset}")
                        continue
                    f = Failure(kind, onset, size, fseed, center_mm=at)
                cases.append(CancelCase(name, obj.index, f))
    return cases, notes


def _plate_box(om: ObjectMap) -> tuple[float, float, float, float]:
    boxes = np.array([o.bbox_mm for o in om.objects])
    return (float(boxes[:, 0].min()), float(boxes[:, 1].min()), float(boxes[:, 2].max()), float(boxes[:, 3].max()))


def run_case(case: CancelCase, tp: Toolpath, om: ObjectMap, image_size: tuple[int, int] = (1280, 720),
             seed: int = 0, max_after: int = 10, tick: Callable[[], None] | None = None,
             follow: int = 0) -> CaseResult:
    """Simulate ``case`` and judge it layer by layer until the first stopping decision.

    Parameters
    ----------
    case : CancelCase
    tp, om : Toolpath, ObjectMap
        The plate ``case.plate`` names.
    image_size : (int, int)
        Simulated camera resolution, px.
    seed : int
        Simulation seed (camera noise, print imperfections).
    max_after : int
        Layers after the onset to wait for a decision before the case counts as ``missed``.
    tick : callable, optional
        Called after each judged layer.
    follow : int
        After a cancel, go on for this many layers as the printer would (the cancelled object left
        out of the simulation after the layer it was cancelled on) and keep the later decisions in
        ``CaseResult.later`` (default 0: stop at the first stopping decision).
    """
    t0 = time.perf_counter()
    kinds = {k: {"action": "cancel_object"} for k in FAILURE_KINDS}
    cfg = resolve_config(None, gcode=observed_square(_plate_box(om)), flags={"policy": {"kinds": kinds}}).config
    tv = cfg.topview.topview()
    truth = default_camera(tv, image_size=image_size)
    sim = PrintSimulator(tp, truth, tv, [case.failure], seed=seed)
    first = sim.frame(0)
    camera = locate_bed(dataclasses.replace(truth, rvec=None, tvec=None), first.photo, cfg.markers, tv)
    pipe = LayerPipeline(tp, camera, cfg, bed_photo=sim.bed_photo())
    policy = PausePolicy(cfg.policy)
    actions = ActionExecutor(_RecordingHost(), om, pipe)
    quiet = quiet_layers(tp, om)
    out = CaseResult(case, om.objects[case.target].name)
    last = min(tp.n_layers - 1, case.failure.onset + max_after)

    def judge(i: int) -> Decision:
        if i in quiet:  # as the monitor: layers that print none of the part are not judged
            res = LayerResult(layer=i, z=tp.layers[i].z, status="skipped", message="prints no part")
        else:
            res = pipe.process(first.photo if i == 0 else sim.frame(i).photo, i)
        if tick is not None:
            tick()
        out.layers = i + 1
        return policy.update(res)

    for i in range(last + 1):
        decision = judge(i)
        if not decision.stops:
            continue
        located = om.locate(tp, decision.regions, decision.layer)
        done = actions.execute(decision, policy)
        out.layer, out.kind, out.reason, out.located = i, decision.kind, done.decision.reason, located.objects
        if done.target is not None:
            out.cancelled = done.target.name
        if i < case.failure.onset:
            out.outcome = "early"
        elif done.target is None:
            out.outcome = "pause"
        else:
            out.outcome = "correct" if done.target.index == case.target else "wrong"
        if follow > 0 and done.target is not None:  # the printer skips the object from the next layer on
            sim.tp = without_objects(tp, om, {done.target.index: i})
            for j in range(i + 1, min(tp.n_layers, i + 1 + follow)):
                later = judge(j)
                if later.action == "none":
                    continue
                carried = actions.execute(later, policy).decision if later.stops else later
                out.later.append((j, later.action, carried.reason))
                if later.stops:
                    break
        break
    out.seconds = time.perf_counter() - t0
    return out


def iter_cases(cases: Sequence[CancelCase], plates: dict[str, tuple[Toolpath, ObjectMap]], *,
               image_size: tuple[int, int] = (1280, 720), seed: int = 0, max_after: int = 10, workers: int = 1,
               progress: Callable[[int, int], None] | None = None) -> Iterator[CaseResult]:
    """:func:`run_case` for every case (on ``workers`` processes), each result as soon as it is ready.

    Results come in the order of ``cases``; case ``k`` is simulated with seed ``seed + k``.
    """
    from layerwatch.evaluate.parallel import map_prints

    tasks = [(c, *plates[c.plate], image_size, seed + k, max_after) for k, c in enumerate(cases)]
    weights = [min(c.failure.onset + max_after + 1, plates[c.plate][0].n_layers) for c in cases]
    yield from map_prints(run_case, tasks, weights, workers, progress)


def run_cases(cases: Sequence[CancelCase], plates: dict[str, tuple[Toolpath, ObjectMap]], *,
              image_size: tuple[int, int] = (1280, 720), seed: int = 0, max_after: int = 10, workers: int = 1,
              progress: Callable[[int, int], None] | None = None) -> list[CaseResult]:
    """:func:`iter_cases` as a list (in the order of ``cases``)."""
    return list(iter_cases(cases, plates, image_size=image_size, seed=seed, max_after=max_after, workers=workers,
                           progress=progress))


def tally(results: Iterable[CaseResult]) -> Counter:
    """Outcome -> count."""
    return Counter(r.outcome for r in results)


def _short_reason(reason: str) -> str:
    """The fallback's why (``...; no object cancelled: <why>; paused instead``), or the reason."""
    if "no object cancelled: " in reason:
        return reason.split("no object cancelled: ", 1)[1].replace("; paused instead", "")
    return reason


def summary_table(results: Sequence[CaseResult]) -> str:
    """Markdown: outcomes per plate and per kind, then every fall-back to pause and every wrong cancel."""
    outcomes = ("correct", "pause", "wrong", "early", "missed")
    lines = ["| plate / kind | cases | " + " | ".join(outcomes) + " |", "|---|---:|" + "---:|" * len(outcomes)]
    for key, pick in [*((p, lambda r, p=p: r.case.plate == p) for p in dict.fromkeys(r.case.plate for r in results)),
                      *((k, lambda r, k=k: r.case.failure.type == k)
                        for k in dict.fromkeys(r.case.failure.type for r in results))]:
        sel = [r for r in results if pick(r)]
        c = tally(sel)
        lines.append(f"| {key} | {len(sel)} | " + " | ".join(str(c[o]) for o in outcomes) + " |")
    c = tally(results)
    lines.append(f"| **all** | **{len(results)}** | " + " | ".join(f"**{c[o]}**" for o in outcomes) + " |")
    odd = [r for r in results if r.outcome in ("pause", "wrong", "early")]
    if odd:
        lines += ["", "| case | outcome | layer | why |", "|---|---|---:|---|"]
        lines += [f"| {r.case.label} | {r.outcome}{' ' + r.cancelled if r.cancelled else ''} | {r.layer} | "
                  f"{_short_reason(r.reason)} |" for r in odd]
    return "\n".join(lines)
