"""The empty-bed check, the first-layer inspection and the nothing-extruded check (issue 21), on simulated prints."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.check_settings import BedCheckSettings
from layerwatch.analysis.result import LayerResult
from layerwatch.analysis.scene_change import top_coords
from layerwatch.evaluate.checks import (
    _footprints,
    _setup,
    bed_check_trials,
    extrusion_trials,
    first_layer_trials,
    job_checks,
)
from layerwatch.examples import PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.settings import TopViewSettings
from layerwatch.pipeline.config import recommended_config
from layerwatch.pipeline.policy import PausePolicy, PolicySettings
from layerwatch.pipeline.step import LayerPipeline, judge_layers
from layerwatch.simulate import Failure, PrintSimulator
from layerwatch.simulate.bed_scene import Leftover, StartLight, start_photo

SIZE = (640, 360)


@pytest.fixture(scope="module")
def part():
    tp = read_toolpath(PART_GCODE.read_bytes())
    tv, cam = _setup(tp, SIZE)
    return tp, tv, cam


def test_bed_with_a_hex_key_is_held_and_a_clean_bed_under_new_light_is_not(part):
    tp, tv, cam = part
    sim = PrintSimulator(tp, cam, tv, seed=3)
    checks = job_checks(tp, cam, tv, sim.bed_photo())
    light = StartLight(exposure=1.3, white_balance=(1.08, 0.95, 0.92), light_shift_mm=(20.0, -10.0, 15.0))
    clean = checks.check_bed(start_photo(sim, (), light, 1))
    assert clean is not None and clean.status == "ok" and clean.failed_check == ""
    c = tv.center_mm
    key = Leftover("hex_key", (c[0] + 10, c[1] - 5), 12.0, 0.3)
    held = checks.check_bed(start_photo(sim, (key,), light, 2))
    assert held is not None and held.failed_check == "empty_bed"
    assert held.check_regions and all(r.kind == "foreign_body" for r in held.check_regions)
    x0, y0, x1, y1 = held.check_regions[0].bbox_mm
    assert x0 - 10 <= key.center_mm[0] <= x1 + 10 and y0 - 10 <= key.center_mm[1] <= y1 + 10
    assert checks.image is not None and checks.image.ndim == 3
    decision = PausePolicy(PolicySettings()).update(held)  # layer -1: before the first judged layer
    assert decision.action == "pause" and "not empty" in decision.reason


def test_bed_check_off_without_bed_photo_or_when_disabled(part):
    tp, tv, cam = part
    sim = PrintSimulator(tp, cam, tv, seed=3)
    assert job_checks(tp, cam, tv).check_bed(sim.bed_photo()) is None
    off = job_checks(tp, cam, tv, sim.bed_photo(), bed_check=BedCheckSettings(enabled=False))
    assert off.check_bed(sim.bed_photo()) is None


def test_nothing_extruded_is_flagged_on_the_second_layer_and_not_on_a_clean_print(part):
    tp, _, _ = part
    tv, cam = _setup(tp, (1280, 720))
    fpf = _footprints(tp, tv)
    onset = 11

    def flags(failures):
        sim = PrintSimulator(tp, cam, tv, failures, seed=5)
        checks = job_checks(tp, cam, tv)
        out = {}
        for i in range(onset - 3, onset + 2):
            res = LayerResult(layer=i, z=float(tp.layers[i].z))
            checks.after_layer(res, sim.frame(i).photo, i, fpf)
            out[i] = res
        return out

    bad = flags([Failure("nothing_extruded", onset=onset)])
    assert bad[onset + 1].failed_check == "nothing_extruded"
    assert bad[onset + 1].check_regions[0].kind == "nothing_extruded"
    assert not any(bad[i].failed_check for i in range(onset - 3, onset))
    assert not any(r.failed_check for r in flags([]).values())


def test_pipeline_step_reports_nothing_extruded_and_the_policy_pauses(part):
    tp, _, _ = part
    tv, cam = _setup(tp, (1280, 720))
    cfg = recommended_config().model_copy(update={"topview": TopViewSettings(
        center_mm=tuple(tv.center_mm), width_mm=tv.width_mm, height_mm=tv.height_mm)})
    sim = PrintSimulator(tp, cam, tv, [Failure("nothing_extruded", onset=11)], seed=5)
    pipe = LayerPipeline(tp, cam, cfg, bed_photo=sim.bed_photo())
    policy = PausePolicy(cfg.policy)
    out = {i: (res, d) for i, (res, d) in zip(range(8, 13), judge_layers(
        pipe, policy, ((i, sim.frame(i).photo) for i in range(8, 13))), strict=True)}
    assert [i for i, (r, _) in out.items() if r.failed_check] == [12]
    assert min(i for i, (_, d) in out.items() if d.stops) <= 12  # the HOG comparison may see it first (layer 11)
    res = out[12][0]
    assert res.check_regions[0].kind == "nothing_extruded"
    decision = PausePolicy(cfg.policy).update(res)  # on its own, the failed check pauses at once
    assert decision.action == "pause" and "nothing extruded" in decision.reason


def test_first_layer_nothing_extruded_and_missing_lines_fail_a_clean_one_passes(part):
    tp, tv, cam = part
    fpf = _footprints(tp, tv)
    verdicts = {}
    for name, fails in {"clean": [], "nothing": [Failure("nothing_extruded", onset=0)],
                        "missing": [Failure("infill_defect", onset=0, size_mm=12.0, seed=4)]}.items():
        sim = PrintSimulator(tp, cam, tv, fails, seed=2)
        checks = job_checks(tp, cam, tv, sim.bed_photo())
        res = LayerResult(layer=0, z=float(tp.layers[0].z))
        checks.after_layer(res, sim.frame(0).photo, 0, fpf)
        verdicts[name] = res
    assert verdicts["clean"].failed_check == ""
    assert verdicts["nothing"].failed_check == "first_layer"
    assert {r.kind for r in verdicts["nothing"].check_regions} == {"nothing_extruded"}
    assert verdicts["missing"].failed_check == "first_layer"
    assert PausePolicy(PolicySettings(skip_first_layers=1)).update(verdicts["nothing"]).stops


@pytest.mark.slow
def test_rates_on_a_small_sample():
    """The benchmark's rates (benchmarks/eval_checks.py) on a small sample: all caught, no false hold."""
    false, caught = bed_check_trials(PART_GCODE, 12, 12, seed=7, size=SIZE)
    assert false.hits == 0 and false.cases == 12
    assert caught.hits >= 11, caught.line("caught")
    caught, false = extrusion_trials([PART_GCODE], 6, seed=7)  # 1280 x 720: the bead texture must be resolved
    assert caught.hits >= 5 and false.hits == 0, (caught.line("caught"), false.line("false"))
    fl = first_layer_trials(PART_GCODE, 2, seed=7, size=SIZE)
    assert fl["nothing_extruded"].hits == 2 and fl["missing_lines"].hits >= 1
    assert np.isfinite(fl["clean"].rate)


def test_plane_maps_are_built_once_per_frame_and_not_held_after(part):
    """Within ``JobChecks.frame()`` the nothing-extruded check and the layer-change channel read the same plane
    maps (built once, the same values as outside a frame); nothing is held after it."""
    tp, tv, cam = part
    checks = job_checks(tp, cam, tv)
    outside = checks.maps
    assert checks._maps is not None and checks._maps[0] is None  # A is rebuilt per call (rays that go down)
    with checks.frame():
        first, again = checks.maps, checks.maps
        assert first[0] is again[0]
        assert all(np.array_equal(a, b) for a, b in zip(first, outside, strict=True))
        planes = checks.planes()
        assert checks.planes() is planes and planes == {}
        fp = np.zeros(tv.shape, bool)
        fp[280:320, 270:330] = True
        area, surface = checks._layer_surface(fp, 2.0, first, 0.4)
        kept = planes[2.0]  # the plane's coordinates, computed once, for the layer-change channel too
        assert all(np.array_equal(a, b) for a, b in zip(kept, top_coords(outside, 2.0), strict=True))
        assert checks._layer_surface(fp, 2.0, first, 0.4)[1].tolist() == surface.tolist() and planes[2.0] is kept
    assert checks._frame_maps is None and checks.maps[0] is not first[0]
    assert checks._frame_planes is None and checks.planes() == {} and checks.planes() is not planes
    assert checks._layer_surface(fp, 2.0, checks.maps, 0.4)[1].tolist() == surface.tolist()  # as outside a frame
    assert surface.any()
