"""Evaluation of the checks on simulated prints: empty bed, first layer, nothing extruded.

Every figure is a count over simulated cases made by :mod:`layerwatch.simulate`
(its own camera, light and sensor; :mod:`layerwatch.simulate.bed_scene` for
leftover objects and the light since the bed photo) and judged by the same
functions the pipeline runs (:class:`~layerwatch.pipeline.checks.JobChecks`).
``benchmarks/eval_checks.py`` prints them for the issue's sample sizes; the
tests run smaller samples.

* :func:`bed_check_trials`: clean starts under changed light (exposure 0.7-1.4 x,
  white balance +-10 %, the spot light moved ~30 mm, brighter or dimmer) and
  starts with one leftover object of 10-40 mm, on every bed/filament variant
  of :data:`~layerwatch.simulate.bed_scene.BED_VARIANTS`; an object is caught
  when the bed is held with a region within ``CAUGHT_WITHIN_MM`` of it.
* :func:`extrusion_trials`: clean prints (every layer judged: false alarms)
  and nothing-extruded runs starting at a random layer >= 2, caught when a
  layer up to onset + 1 is flagged (within two layers), missed otherwise
  (a flag before the onset counts as a false alarm); the check gets the
  footprints the pipeline gives it (its references' masks).
* :func:`first_layer_trials`: clean first layers, first layers with nothing
  extruded and with missing lines (a patch of 8-14 mm without its infill).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from layerwatch.analysis.check_settings import (
    BedCheckSettings,
    ExtrusionSettings,
    FirstLayerSettings,
)
from layerwatch.analysis.result import LayerResult
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.settings import TopViewSettings
from layerwatch.geometry.warp import TopViewWarper
from layerwatch.pipeline.checks import NOTHING_EXTRUDED, JobChecks, print_reach_mm, print_top_z_mm
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, SimSettings, default_camera
from layerwatch.simulate.bed_scene import BED_VARIANTS, random_leftover, random_light, start_photo
from layerwatch.simulate.raster import solid_area

__all__ = ["CAUGHT_WITHIN_MM", "Counts", "bed_check_trials", "extrusion_trials", "extrusion_trials_compared",
           "first_layer_trials", "job_checks"]

#: a held bed catches the object when a region lies this close to the object's extent, mm
CAUGHT_WITHIN_MM = 10.0


@dataclass
class Counts:
    """Hits out of cases, per group (bed variant, object kind, G-code...)."""

    hits: int = 0
    cases: int = 0
    groups: dict[str, list[int]] = field(default_factory=dict)
    #: the score behind each verdict, where the check has one (the nothing-extruded similarity)
    values: list[float] = field(default_factory=list)

    def add(self, hit: bool, *groups: str) -> None:
        self.hits += int(hit)
        self.cases += 1
        for g in groups:
            row = self.groups.setdefault(g, [0, 0])
            row[0] += int(hit)
            row[1] += 1

    @property
    def rate(self) -> float:
        return self.hits / self.cases if self.cases else float("nan")

    def line(self, name: str) -> str:
        per = ", ".join(f"{g} {h}/{n}" for g, (h, n) in sorted(self.groups.items()))
        return f"{name}: {self.hits}/{self.cases} = {self.rate:.1%}" + (f" ({per})" if per else "")


def _setup(tp: Toolpath, size: tuple[int, int]):
    x0, y0, x1, y1 = tp.bounds
    side = max(90.0, max(x1 - x0, y1 - y0) + 30.0)
    tv = TopViewSettings(center_mm=((x0 + x1) / 2, (y0 + y1) / 2), width_mm=side, height_mm=side).topview()
    return tv, default_camera(tv, image_size=size)


def job_checks(tp: Toolpath, camera, tv, bed_photo=None, **sections) -> JobChecks:
    """A :class:`JobChecks` of the recommended settings (``sections``: overrides per section)."""
    on = {"bed_check": BedCheckSettings(enabled=True), "first_layer": FirstLayerSettings(enabled=True),
          "extrusion": ExtrusionSettings(enabled=True)}
    cfg = JobConfig(**{**on, **sections})
    return JobChecks(camera, tv, TopViewWarper(camera, tv), cfg, bed_photo, reach_mm=print_reach_mm(tp), top_z_mm=print_top_z_mm(tp))


def _footprints(tp: Toolpath, tv):
    def footprint(j: int):
        sl = tp.layer_slice(j)
        lay = tp.layers[j]
        return solid_area(tp.start[sl], tp.end[sl], tp.width[sl] / 2.0, tv), lay.z - lay.height, lay.z
    return footprint


def _pipeline_footprints(tp: Toolpath, camera, tv):
    """The footprints the pipeline hands the checks: its references' masks (:meth:`LayerPipeline.footprint`)."""
    cfg = JobConfig(topview=TopViewSettings(center_mm=tuple(tv.center_mm), width_mm=tv.width_mm, height_mm=tv.height_mm))
    pipe = LayerPipeline(tp, camera, cfg, memo=tp.n_layers)
    assert pipe.topview.shape == tv.shape, "the pipeline's top view must be the trials' own"
    return pipe.footprint


def bed_check_trials(gcode: str | Path, n_clean: int, n_objects: int, seed: int = 0,
                     size: tuple[int, int] = (1280, 720)) -> tuple[Counts, Counts]:
    """False holds over ``n_clean`` clean starts and objects caught out of ``n_objects`` (module notes).

    Returns
    -------
    false_holds, caught : Counts
        Grouped by bed variant (and object kind for ``caught``).
    """
    tp = read_toolpath(Path(gcode).read_bytes())
    tv, cam = _setup(tp, size)
    rng = np.random.default_rng(seed)
    false, caught = Counts(), Counts()
    variants = list(BED_VARIANTS.items())
    for k in range(max(n_clean, n_objects)):
        name, upd = variants[k % len(variants)]
        sim = PrintSimulator(tp, cam, tv, seed=seed * 1000 + k, settings=SimSettings(**upd))
        checks = job_checks(tp, cam, tv, sim.bed_photo())
        if k < n_clean:
            res = checks.check_bed(start_photo(sim, (), random_light(rng), 2 * k))
            false.add(bool(res and res.failed_check), name)
        if k < n_objects:
            obj = random_leftover(tv, rng, avoid_mm=tv.corners_mm)
            res = checks.check_bed(start_photo(sim, (obj,), random_light(rng), 2 * k + 1))
            near = res is not None and any(
                np.hypot(max(r.bbox_mm[0] - obj.center_mm[0], obj.center_mm[0] - r.bbox_mm[2], 0.0),
                         max(r.bbox_mm[1] - obj.center_mm[1], obj.center_mm[1] - r.bbox_mm[3], 0.0))
                <= CAUGHT_WITHIN_MM + obj.size_mm / 2 for r in res.check_regions)
            caught.add(bool(res and res.failed_check) and near, name, obj.kind,
                       "10-15 mm" if obj.size_mm < 15 else "15-40 mm")
    return false, caught


def _judge(checks: Sequence[JobChecks], sim: PrintSimulator, layers: Sequence[int],
           footprint) -> list[dict[int, tuple[bool, float]]]:
    """Per checker, per layer of ``layers`` (photographed in order, each photo judged by every checker):
    flagged ``nothing_extruded``, and the surface similarity."""
    out: list[dict[int, tuple[bool, float]]] = [{} for _ in checks]
    for i in layers:
        photo = sim.frame(i).photo
        for c, got in zip(checks, out, strict=True):
            res = LayerResult(layer=i, z=float(sim.tp.layers[i].z))
            c.after_layer(res, photo, i, footprint)
            got[i] = (res.failed_check == NOTHING_EXTRUDED, c.similarity[0])
    return out


def extrusion_trials(gcodes: Sequence[str | Path | Toolpath], n_cases: int, seed: int = 0, clean_prints: int = 1,
                     max_layers: int = 80, size: tuple[int, int] = (1280, 720)) -> tuple[Counts, Counts]:
    """Nothing-extruded runs caught within two layers, and false alarms on clean prints (module notes).

    The recommended ``[extrusion]`` settings; :func:`extrusion_trials_compared` judges the same
    photos with several.

    Parameters
    ----------
    gcodes : sequence of path or Toolpath
        The prints (cases cycle through them), e.g. a G-code file or the simulator's
        :func:`~layerwatch.simulate.parts.window_part`. The check gets the footprints the
        pipeline gives it (its references' masks).
    n_cases : int
        Nothing-extruded runs.
    clean_prints : int
        Clean prints per G-code (seeds), each judged on its first ``max_layers`` layers.

    Returns
    -------
    caught : Counts
        Per G-code.
    false_alarms : Counts
        Clean layers flagged (hits) over clean layers judged, per G-code; ``values`` also holds the
        layers not judged (``nan``: surface too small, fewer than two photos before).
    """
    return extrusion_trials_compared(gcodes, n_cases, [ExtrusionSettings(enabled=True)], seed, clean_prints,
                                     max_layers, size)[0]


def extrusion_trials_compared(gcodes: Sequence[str | Path | Toolpath], n_cases: int,
                              settings: Sequence[ExtrusionSettings], seed: int = 0, clean_prints: int = 1,
                              max_layers: int = 80, size: tuple[int, int] = (1280, 720)) -> list[tuple[Counts, Counts]]:
    """:func:`extrusion_trials` for several ``[extrusion]`` settings on the same photos: ``(caught, false)`` for each."""
    rng = np.random.default_rng(seed)
    counts = [(Counts(), Counts()) for _ in settings]

    def checkers(tp, cam, tv) -> list[JobChecks]:
        return [job_checks(tp, cam, tv, extrusion=st) for st in settings]

    for g, path in enumerate(gcodes):
        tp = path if isinstance(path, Toolpath) else read_toolpath(Path(path).read_bytes())
        tv, cam = _setup(tp, size)
        fpf = _pipeline_footprints(tp, cam, tv)
        name = Path(str(tp.source)).stem.strip("<>") if isinstance(path, Toolpath) else Path(path).stem
        n = min(tp.n_layers, max_layers)
        for c in range(clean_prints):
            sim = PrintSimulator(tp, cam, tv, seed=seed * 100 + c)
            for (_, false), judged in zip(counts, _judge(checkers(tp, cam, tv), sim, range(n), fpf), strict=True):
                for flag, value in judged.values():
                    false.values.append(value)
                    if np.isfinite(value):  # a layer the check judged (its surface large enough, 2 photos before)
                        false.add(flag, name)
        for k in range(g, n_cases, len(gcodes)):
            onset = int(rng.integers(2, n - 1))
            sim = PrintSimulator(tp, cam, tv, [Failure("nothing_extruded", onset=onset)], seed=seed * 100 + 50 + k)
            layers = range(max(onset - 2, 0), onset + 2)
            for (caught, false), judged in zip(counts, _judge(checkers(tp, cam, tv), sim, layers, fpf), strict=True):
                for i, (flag, value) in judged.items():
                    if i < onset and np.isfinite(value):  # clean layers before the onset that were judged
                        false.add(flag, name)
                        false.values.append(value)
                caught.add(any(judged[i][0] for i in (onset, onset + 1)), name)
                caught.values.append(judged[onset + 1][1])
    return counts


def first_layer_trials(gcode: str | Path, n_each: int, seed: int = 0,
                       size: tuple[int, int] = (1280, 720)) -> dict[str, Counts]:
    """First-layer verdicts: ``"clean"`` (hits = false fails), ``"nothing_extruded"`` and ``"missing_lines"``
    (hits = caught), ``n_each`` cases each, cycling through the bed variants."""
    tp = read_toolpath(Path(gcode).read_bytes())
    tv, cam = _setup(tp, size)
    fpf = _footprints(tp, tv)
    rng = np.random.default_rng(seed)
    out = {"clean": Counts(), "nothing_extruded": Counts(), "missing_lines": Counts()}
    variants = list(BED_VARIANTS.items())
    for k in range(n_each):
        name, upd = variants[k % len(variants)]
        cases = {"clean": [], "nothing_extruded": [Failure("nothing_extruded", onset=0)],
                 "missing_lines": [Failure("infill_defect", onset=0, size_mm=float(rng.uniform(8, 14)),
                                           seed=int(rng.integers(2**31)))]}
        for case, fails in cases.items():
            sim = PrintSimulator(tp, cam, tv, fails, seed=seed * 1000 + k, settings=SimSettings(**upd))
            checks = job_checks(tp, cam, tv, sim.bed_photo())
            res = LayerResult(layer=0, z=float(tp.layers[0].z))
            checks.after_layer(res, sim.frame(0).photo, 0, fpf)
            out[case].add(res.failed_check == "first_layer", name)
    return out
