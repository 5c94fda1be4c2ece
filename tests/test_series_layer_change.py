"""The "changed as predicted" channel in the per-layer step (issue 18): series only, no verdict without a usable
previous photo, off with the paper's settings, and never a pause from a black or skipped photo."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.examples import PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.settings import TopViewSettings
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline, judge_layers
from layerwatch.simulate import PrintSimulator
from layerwatch.simulate.scene import default_camera


@pytest.fixture(scope="module")
def job():
    tp = read_toolpath(PART_GCODE.read_bytes())
    x0, y0, x1, y1 = tp.bounds
    square = {"center_mm": ((x0 + x1) / 2, (y0 + y1) / 2), "width_mm": 90.0, "height_mm": 90.0}
    tv = TopViewSettings(**square).topview()
    cam = default_camera(tv, image_size=(1280, 720))
    sim = PrintSimulator(tp, cam, tv, seed=7)
    photos = {i: sim.frame(i).photo for i in (10, 11, 12, 13)}
    return tp, cam, square, sim.bed_photo(), photos


def _pipe(job, paper=False, **sections):
    tp, cam, square, bed, _ = job
    cfg = resolve_config(recommended=not paper, flags={"topview": square, **sections}).config
    return LayerPipeline(tp, cam, cfg, bed_photo=bed)


def test_the_first_photo_is_not_judged_the_next_one_is(job):
    pipe = _pipe(job)
    photos = job[4]
    first, second = pipe.process(photos[10], 10), pipe.process(photos[11], 11)
    assert first.layer_change is not None and not first.layer_change.judged
    assert "no earlier photo" in first.layer_change.note
    lc = second.layer_change
    assert lc is not None and lc.judged and lc.previous_layer == 10 and lc.px_judged > 1000
    assert lc.parallax_px > 0 and "layer_change" in second.timings_ms
    assert not [r for r in second.regions if r.kind in ("thin_wall", "infill_defect") and r.mean_similarity == 0.0]
    pipe.new_print(job[3])  # a new print (or the single-photo mode): no previous photo any more
    again = pipe.process(photos[12], 12)
    assert again.layer_change is not None and not again.layer_change.judged


def test_off_with_the_paper_settings(job):
    pipe = _pipe(job, paper=True)
    assert pipe.layer_change is None
    res = pipe.process(job[4][11], 11)
    assert res.layer_change is None


def test_a_black_photo_in_the_series_is_rejected_and_the_next_is_judged_against_the_last_good_one(job):
    # the scene channel rejects the black frame (an alert, never a pause): layer 13 is compared with
    # layer 11's photo, a skipped layer's parallax
    pipe = _pipe(job)
    photos = job[4]
    frames = [(10, photos[10]), (11, photos[11]), (12, np.zeros_like(photos[12])), (13, photos[13])]
    out = list(judge_layers(pipe, PausePolicy(pipe.config.policy), frames))
    assert not any(d.stops for _, d in out), [(r.layer, r.status, d.action, d.reason) for r, d in out]
    assert out[2][0].status == "error" and out[2][0].layer_change is None
    last = out[-1][0].layer_change
    assert last is not None and last.judged and last.previous_layer == 11
    assert not [r for res, _ in out for r in res.regions if r.kind in ("thin_wall", "infill_defect")
                and r.mean_similarity == 0.0]


def test_after_an_analysed_black_photo_the_next_photo_gets_no_verdict(job):
    # without the scene channel nothing rejects the black frame; it becomes the previous photo, and
    # the next one has nothing to calibrate the noise on: "not judged", no region from this channel
    pipe = _pipe(job, scene={"enabled": False})
    photos = job[4]
    pipe.process(photos[11], 11)
    pipe.process(np.zeros_like(photos[12]), 12)
    res = pipe.process(photos[13], 13)
    assert res.layer_change is not None and not res.layer_change.judged and "texture" in res.layer_change.note
    assert res.layer_change.unchanged_mm2 == 0.0


def test_on_in_the_recommended_settings_off_in_the_paper_settings_and_every_number_has_a_dashboard_range():
    from layerwatch.analysis.layer_change import LayerChangeSettings
    from layerwatch.web.settings import RANGES

    assert resolve_config().config.layer_change.enabled
    assert not resolve_config(recommended=False).config.layer_change.enabled
    numbers = [k for k, v in LayerChangeSettings().model_dump().items() if not isinstance(v, bool)]
    assert numbers and all(f"layer_change.{k}" in RANGES for k in numbers)


def test_a_layer_the_typer_found_moved_gets_no_thin_wall_or_infill_region(job, monkeypatch):
    """A shifted layer leaves its planned place as it was: that is the motion's area (the typer's moved
    outline), not a gap in the walls or infill. With the thresholds at 0 (every pixel that fits the previous
    photo at least as well in place as shifted counts), a clean layer gets the channel's regions and the
    shifted layer none."""
    import layerwatch.pipeline.layer_change as lc_module
    from layerwatch.analysis.failure_kinds import MOVED_KINDS
    from layerwatch.simulate import Failure

    monkeypatch.setattr(lc_module, "MAX_UNCHANGED_SHARE", 1.0)
    tp, cam, square, bed, _ = job
    tv = TopViewSettings(**square).topview()
    shifted = PrintSimulator(tp, cam, tv, (Failure("layer_shift", onset=12, size_mm=4.0, seed=1),), seed=7)
    pipe = _pipe(job, layer_change={"min_ncc": 0.0, "min_gain": 0.0})
    results = [pipe.process(shifted.frame(i).photo, i) for i in (10, 11, 12)]
    clean, moved = results[1], results[2]
    assert any(r.kind in MOVED_KINDS for r in moved.regions), "the typer did not find the shift"
    assert clean.layer_change is not None and clean.layer_change.added_mm2 + clean.layer_change.unchanged_mm2 > 0
    assert moved.layer_change is not None and "the part moved" in moved.layer_change.note
    assert moved.layer_change.unchanged_mm2 == 0.0


def test_the_moved_area_that_switches_the_channel_off_is_the_policy_s_current_one(job, monkeypatch):
    """A settings edit of ``[policy] min_area_mm2`` while the pipeline runs applies from the next layer on:
    the shifted layer that switched the channel off at the default area leaves it on once the area is raised
    above the shift's (the pipeline not rebuilt), whether the config is replaced or its section edited."""
    import layerwatch.pipeline.layer_change as lc_module
    from layerwatch.simulate import Failure

    monkeypatch.setattr(lc_module, "MAX_UNCHANGED_SHARE", 1.0)
    tp, cam, square, bed, _ = job
    tv = TopViewSettings(**square).topview()
    shifted = PrintSimulator(tp, cam, tv, (Failure("layer_shift", onset=12, size_mm=4.0, seed=1),), seed=7)
    pipe = _pipe(job, layer_change={"min_ncc": 0.0, "min_gain": 0.0})
    assert pipe.layer_change is not None and pipe.layer_change.moved_min_mm2 == pipe.config.policy.min_area_mm2
    for i in (10, 11):
        pipe.process(shifted.frame(i).photo, i)
    pipe.config = pipe.config.model_copy(update={"policy": pipe.config.policy.model_copy(update={"min_area_mm2": 1e4})})
    assert pipe.layer_change.moved_min_mm2 == 1e4
    moved = pipe.process(shifted.frame(12).photo, 12)
    assert moved.layer_change is not None and moved.layer_change.judged
    assert "the part moved" not in moved.layer_change.note
    pipe.config.policy.min_area_mm2 = 1.0  # an edit in place reaches it too
    assert pipe.layer_change.moved_min_mm2 == 1.0


def test_small_moved_regions_leave_the_channel_on_apart_from_their_outline(job, monkeypatch):
    """Moved regions of less than the policy's ``min_area_mm2`` together (here raised above the shift's) do not
    switch the channel off for the layer: only the unchanged pixels within 1 mm of their outline are left out."""
    import layerwatch.pipeline.layer_change as lc_module
    from layerwatch.analysis.failure_kinds import MOVED_KINDS
    from layerwatch.analysis.layer_change import moved_pixels
    from layerwatch.simulate import Failure

    monkeypatch.setattr(lc_module, "MAX_UNCHANGED_SHARE", 1.0)
    seen = []
    real = lc_module.unchanged_regions
    monkeypatch.setattr(lc_module, "unchanged_regions", lambda top, *a: seen.append(top) or real(top, *a))
    tp, cam, square, bed, _ = job
    tv = TopViewSettings(**square).topview()
    shifted = PrintSimulator(tp, cam, tv, (Failure("layer_shift", onset=12, size_mm=4.0, seed=1),), seed=7)
    pipe = _pipe(job, layer_change={"min_ncc": 0.0, "min_gain": 0.0}, policy={"min_area_mm2": 1e4})
    moved = [pipe.process(shifted.frame(i).photo, i) for i in (10, 11, 12)][-1]
    regions = [r for r in moved.regions if r.kind in MOVED_KINDS]
    assert regions and sum(r.area_mm2 for r in regions) < 1e4
    assert moved.layer_change is not None and "the part moved" not in moved.layer_change.note
    top = seen[-1]
    assert top.any(), "the channel judged the pixels away from the moved part"
    k = 2 * int(round(lc_module.MOVED_MARGIN_MM * tv.px_per_mm)) + 1
    near = cv2.dilate(moved_pixels(regions, tv).view(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    assert not (top & (near > 0)).any()
