"""The camera's region of interest (layerwatch.geometry.roi) and the camera-fault gate on it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from layerwatch.analysis.frame_quality import (
    FrameQualitySettings,
    assess_frame,
    blockiness,
    grey_of,
    noise_sigma,
)
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.roi import REACH_PAD_MM, ROI_ALIGN, bed_roi
from layerwatch.geometry.synthetic import project_points
from layerwatch.monitor.frame_checks import FrameChecks
from layerwatch.pipeline.checks import print_reach_mm, print_top_z_mm
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import PrintSimulator, default_camera


@pytest.fixture(scope="module")
def job():
    cfg = resolve_config(PART_CONFIG).config
    tp = read_toolpath(PART_GCODE)
    return cfg, tp, cfg.topview.topview()


@pytest.mark.parametrize("elevation", [30.0, 45.0, 60.0])
@pytest.mark.parametrize("size", [(1920, 1080), (1280, 720)])
@pytest.mark.parametrize("top", [None, 50.0])  # the example part's top (9.9 mm), and a tall print over its reach
def test_the_box_holds_the_square_on_the_bed_and_the_prints_prism_and_is_aligned(job, elevation, size, top):
    _, tp, tv = job
    cam = default_camera(tv, image_size=(1280, 720), elevation_deg=elevation)
    top = print_top_z_mm(tp) if top is None else top
    reach = print_reach_mm(tp)
    rows, cols = bed_roi(cam, tv, top, size, reach_mm=reach)
    w, h = size
    rng = np.random.default_rng(0)
    (x0, y0), (x1, y1) = tv.corners_mm.min(axis=0), tv.corners_mm.max(axis=0)
    bed = np.c_[rng.uniform(x0, x1, 500), rng.uniform(y0, y1, 500), np.zeros(500)]  # anything on the bed
    p = REACH_PAD_MM
    prism = np.c_[rng.uniform(reach[0] - p, reach[2] + p, 500), rng.uniform(reach[1] - p, reach[3] + p, 500),
                  rng.uniform(0, top, 500)]  # anything of the print
    uv = project_points(cam.scaled_to(size), np.vstack([bed, prism]))
    uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)]  # what the camera sees of them
    assert len(uv) > 500
    assert np.all((uv[:, 0] >= cols.start) & (uv[:, 0] < cols.stop) & (uv[:, 1] >= rows.start) & (uv[:, 1] < rows.stop))
    assert rows.start % ROI_ALIGN == 0 and cols.start % ROI_ALIGN == 0
    assert rows.stop % ROI_ALIGN == 0 or rows.stop == h
    assert cols.stop % ROI_ALIGN == 0 or cols.stop == w
    share = (rows.stop - rows.start) * (cols.stop - cols.start) / (w * h)
    assert 0.3 < share < 0.75  # the room around the printer is left out


def test_no_pose_or_no_top_is_the_whole_frame(job):
    _, _, tv = job
    cam = default_camera(tv)
    assert bed_roi(cam, tv, float("nan"), (1280, 720)) == (slice(0, 720), slice(0, 1280))
    bare = dataclasses.replace(cam, rvec=None, tvec=None)
    assert bed_roi(bare, tv, 10.0, (1280, 720)) == (slice(0, 720), slice(0, 1280))


def _frames(job, n=3):
    cfg, tp, tv = job
    cam = default_camera(tv)
    sim = PrintSimulator(tp, cam, tv, [], seed=2)
    return LayerPipeline(tp, cam, cfg), [sim.frame(i).photo for i in range(n)]


def test_the_gate_measures_noise_blocking_and_repeats_on_the_box_and_exposure_sharpness_on_the_whole(job):
    pipe, frames = _frames(job)
    checks = FrameChecks(pipe, FrameQualitySettings(), 3)
    box = checks.roi(frames[1].shape)
    assert box is not None
    q, whole = assess_frame(frames[1], frames[0], box=box), assess_frame(frames[1], frames[0])
    for k in ("p1", "p99", "bright", "sharpness"):
        assert q.figures[k] == whole.figures[k]
    grey = grey_of(frames[1])
    assert q.figures["noise"] == noise_sigma(grey[box])
    assert q.figures["blockiness"] == blockiness(grey[box])
    assert FrameChecks(pipe, FrameQualitySettings(roi=False), 3).roi(frames[1].shape) is None


def test_a_repeat_is_refused_though_the_room_behind_the_printer_changed(job):
    """A lagging stream sends the previous picture again while someone walks by behind the printer: outside the
    box the frame changed, so the whole-frame change hides the repeat; the box's does not."""
    pipe, frames = _frames(job)
    checks = FrameChecks(pipe, FrameQualitySettings(), 3)
    box = checks.roi(frames[1].shape)
    again = frames[1].copy()
    rng = np.random.default_rng(1)
    again[: box[0].start] = rng.integers(0, 256, again[: box[0].start].shape, dtype=np.uint8)  # above the box
    assert checks.gate(1, 0.3, frames[1]) is None
    refused = checks.gate(2, 0.6, again)
    assert refused is not None and "same picture" in refused.message
    off = FrameChecks(pipe, FrameQualitySettings(roi=False), 3)
    assert off.gate(1, 0.3, frames[1]) is None
    assert off.gate(2, 0.6, again) is None  # the whole frame's change hid it
