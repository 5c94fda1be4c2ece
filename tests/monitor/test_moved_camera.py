"""A camera moved since calibration: the bed markers say how far, and the analysis undoes it (no pause on a
clean print), while a part that moved on the bed is still never registered away."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.frame_quality import marker_offset_px
from layerwatch.analysis.view_shift import ViewShift, marker_offset_top_px
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.synthetic import project_points
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import PrintSimulator, default_camera


def test_marker_offset_is_the_median_move_of_the_markers_seen():
    expected = np.array([[100.0, 100.0], [900.0, 110.0], [120.0, 600.0], [880.0, 620.0]])
    found = expected + [4.0, -2.0]
    found[3] += [0.6, 0.4]  # one dot refined a little off
    off = marker_offset_px(np.vstack([found, [[500.0, 300.0]]]), expected, 50.0)  # and a false detection
    assert off == pytest.approx((4.0, -2.0))
    assert marker_offset_px(found[:1], expected, 50.0) is None  # one marker: no verdict
    assert marker_offset_px(found + 100.0, expected, 50.0) is None  # none within the search radius


def test_the_markers_offset_in_the_top_view_is_the_projection_of_a_bed_move():
    cfg = resolve_config(PART_CONFIG).config
    tv = cfg.topview.topview()
    cam = default_camera(tv, image_size=(1920, 1080))
    at, z, d_mm = (float(tv.center_mm[0]), float(tv.center_mm[1])), 4.0, np.array([0.3, -0.5])
    p = project_points(cam, np.array([[at[0], at[1], z], [at[0] + d_mm[0], at[1] + d_mm[1], z]]))
    got = marker_offset_top_px(cam, tv, at, z, tuple(p[1] - p[0]), (1920, 1080))
    want = tv.to_px(np.array(at) + d_mm) - tv.to_px(np.array(at))
    assert got == pytest.approx(tuple(want), abs=0.05)
    half = marker_offset_top_px(cam, tv, at, z, tuple((p[1] - p[0]) / 2), (960, 540))  # the same move at half size
    assert half == pytest.approx(got, abs=0.05)


def test_view_shift_starts_from_the_markers_and_never_registers_a_part_that_moved_on_the_bed():
    vs = ViewShift(max_px=4.0)
    assert vs.update(None, markers=(5.2, -3.1)) == (5, -3)  # the markers alone: a camera moved past max_px
    assert vs.update((5.9, -3.4), markers=(5.2, -3.1)) == (6, -3)  # the part agrees within a pixel
    vs.reset()
    for _ in range(3):
        got = vs.update((9.0, 0.3), markers=(0.1, 0.2))  # the part moved ~1.4 mm, the camera did not
    assert got == (0, 0)
    vs.reset()
    assert vs.update((1.33, 1.32), markers=(0.0, 0.4)) == (1, 1)  # markers that agree change nothing
    assert vs.update(None, markers=(0.0, 0.4)) == (1, 1)


@pytest.mark.slow
def test_a_clean_print_under_a_camera_moved_past_the_registration_limit_does_not_pause():
    """The 1080p camera 3 px right and 3 px up of its calibrated pose (~4.1 top-view px at the print, past
    ``register_mm`` 0.6 mm = 4 px; the gate passes markers up to 12 px off): the farm benchmark's printer 318
    paused the clean example part at layer 2 before the markers' offset was handed to the analysis."""
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    cam = default_camera(cfg.topview.topview(), image_size=(1920, 1080))
    sim = PrintSimulator(tp, cam, cfg.topview.topview(), (), seed=1)
    layers = 6
    gcode = "".join(f"G1 Z{tp.layers[i].z:.2f}\n@layerwatch snapshot layer={i} z={tp.layers[i].z:.2f}\n"
                    for i in range(layers)).encode()
    photos = [np.roll(sim.frame(i).photo, (-3, 3), axis=(0, 1)) for i in range(layers)]
    pipe = LayerPipeline(tp, cam, cfg.for_camera(cam), memo=2)
    mon = Monitor(VirtualPrinter(gcode, name="moved.gcode"), SimCamera(lambda i: photos[i]), pipe,
                  PausePolicy(cfg.policy), wait_for_verdict=True, faults=cfg.faults, frame_quality=cfg.frame_quality)
    rep = mon.run(poll_s=0.0)
    assert len(rep.results) == layers and all(r.status == "ok" for r in rep.results), [r.message for r in rep.results]
    assert rep.pauses == 0 and rep.alerts == 0 and rep.camera_faults == 0, [(r.layer, r.anomaly_ratio) for r in rep.results]
    assert all(r.anomaly_ratio < cfg.policy.pause_ratio for r in rep.results), [r.anomaly_ratio for r in rep.results]
    # undone from the first photo on, toward the right and up (each photo's estimate moves it by a pixel or so)
    assert all(r.view_shift_px[0] >= 1 and r.view_shift_px[1] <= -2 for r in rep.results), \
        [r.view_shift_px for r in rep.results]


def test_the_gate_finds_the_pipeline_that_takes_the_markers_through_its_wrappers():
    """The monitor's pipeline may be an image store's wrapper (attributes passed on) or a farm's pool pipeline (the
    job's own one as ``local``): the markers' offset reaches the LayerPipeline either way, and a pipeline
    without ``markers_moved`` (a test double, another driver) gets nothing."""
    from layerwatch.monitor.frame_checks import _markers_sink

    class Job:
        def __init__(self):
            self.got = []

        def markers_moved(self, offset, size):
            self.got.append((offset, size))

    class Wrapper:
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            return getattr(self.inner, name)

    class Pool:
        def __init__(self, local):
            self.local = local

    for make in (lambda j: j, Wrapper, Pool, lambda j: Wrapper(Pool(j))):
        job = Job()
        sink = _markers_sink(make(job))
        assert sink is not None
        sink((1.0, -2.0), (1920, 1080))
        assert job.got == [((1.0, -2.0), (1920, 1080))]
    assert _markers_sink(object()) is None


def test_an_offset_that_is_not_a_finite_pair_is_taken_as_no_markers():
    """Bad input at the edge: a NaN or infinite offset (a detection gone wrong), or not a pair, assumes nothing."""
    vs, ref = ViewShift(max_px=4.0), ViewShift(max_px=4.0)
    for bad in ((float("nan"), 1.0), (float("inf"), 0.0)):
        assert vs.update((2.2, 1.7), markers=bad) == ref.update((2.2, 1.7))
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    cam = default_camera(cfg.topview.topview(), image_size=(1920, 1080))
    pipe = LayerPipeline(tp, cam, cfg.for_camera(cam), memo=2)
    for bad in ((float("nan"), 1.0), (1.0, 2.0, 3.0), None):
        pipe.markers_moved((3.0, -2.0), (1920, 1080))
        pipe.markers_moved(bad, (1920, 1080))
        assert pipe._markers is None, bad
    pipe.markers_moved((3.0, -2.0), (1920, 1080))
    assert pipe._markers == ((3.0, -2.0), (1920, 1080))
