"""LayerPipeline on simulated photos: clean vs failed layers, bad photos, references."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.render.fast import StackRenderer
from layerwatch.simulate import Failure, default_camera, simulate_layer
from layerwatch.simulate.parts import box_part

LAYER = 7


@pytest.fixture(scope="module")
def job():
    # block threshold 0.5: on simulated photos the paper's 0.7 flags ~half of a clean
    # layer (docs/evaluation/report.md); 0.5 separates clean from failed layers here
    cfg = JobConfig(analysis={"threshold": 0.5})
    tv = cfg.topview.topview()
    cam = default_camera(tv, image_size=(1280, 720))
    tp = box_part(size_mm=24.0, height_mm=3.0, layer_h=0.3)
    return tp, cam, cfg, tv


@pytest.fixture(scope="module")
def pipe(job):
    tp, cam, cfg, _ = job
    return LayerPipeline(tp, cam, cfg)


def _frame(job, failures=()):
    tp, cam, _, tv = job
    return simulate_layer(tp, LAYER, cam, tv, failures, seed=3)


def test_clean_low_failures_high(job, pipe):
    clean = pipe.process(_frame(job).photo, LAYER)
    assert clean.status == "ok", clean.message
    assert clean.layer == LAYER and clean.z == pytest.approx(job[0].layers[LAYER].z)
    for f in (Failure("spaghetti", onset=5, size_mm=16.0, seed=1),
              Failure("layer_shift", onset=5, size_mm=3.0, seed=2)):
        bad = pipe.process(_frame(job, (f,)).photo, LAYER)
        assert bad.status == "ok"
        assert bad.anomaly_ratio > clean.anomaly_ratio + 0.15, (f.type, bad.anomaly_ratio, clean.anomaly_ratio)
    assert {"warp", "reference", "analysis", "hog", "total"} <= set(clean.timings_ms)
    assert pipe.last_top is not None and pipe.last_top.shape == job[3].shape


def test_reference_matches_independent_render(job, pipe):
    tp, _, cfg, tv = job
    fresh = StackRenderer(tp, tv, cfg.render).render(LAYER, pipe.camera.center_mm)
    ref = pipe.reference(LAYER)
    assert np.array_equal(ref.image, fresh.image)
    top = StackRenderer(tp, tv, cfg.render).render(LAYER)  # seen from the camera, not from above
    assert not np.array_equal(ref.image, top.image)
    assert np.array_equal(ref.footprint, fresh.mask)
    assert pipe.reference(LAYER) is ref  # memoised


@pytest.mark.parametrize(
    "photo",
    [
        np.zeros((4, 4), np.uint8),  # too small
        np.zeros((720, 1280, 3), np.float64),  # wrong dtype
        np.full((720, 1280, 3), 100.0, np.float32),  # float pixels: 0..1 or 0..255 cannot be told
        np.full((720, 1280, 3), np.nan, np.float32),
        np.zeros((500, 500, 3), np.uint8),  # other aspect ratio than the calibration
        "not an image",
        None,
    ],
)
def test_bad_photo_gives_error_status(pipe, photo):
    res = pipe.process(photo, LAYER)
    assert res.status == "error"
    assert res.message and "\n" not in res.message
    assert res.layer == LAYER
    res.to_json()  # serialisable


def test_bad_layer_index_is_error_not_exception(job, pipe):
    res = pipe.process(_frame(job).photo, 10_000)
    assert res.status == "error" and "does not exist" in res.message
    for index in ("7", 7.0, None, True):
        res = pipe.process(_frame(job).photo, index)
        assert res.status == "error" and "layer index must be an integer" in res.message


def test_a_bug_inside_the_analysis_is_raised_not_reported_as_a_bad_photo(job, monkeypatch):
    """An exception from layerwatch's own code is a bug (the CLI's exit 70, the monitor's pipeline fault),
    not a layer whose photo "could not be analysed"; running out of memory is the layer's error."""
    tp, cam, cfg, _ = job
    photo = _frame(job).photo

    def broken(*args, **kwargs):
        raise TypeError("unsupported operand type(s) for +: 'NoneType' and 'int'")

    monkeypatch.setattr("layerwatch.pipeline.step.analyze_layer", broken)
    with pytest.raises(TypeError, match="NoneType"):
        LayerPipeline(tp, cam, cfg).process(photo, LAYER)

    def no_memory(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr("layerwatch.pipeline.step.analyze_layer", no_memory)
    res = LayerPipeline(tp, cam, cfg).process(photo, LAYER)
    assert res.status == "error" and "out of memory" in res.message and "\n" not in res.message


def test_all_metrics_and_match_camera(job):
    tp, cam, cfg, _ = job
    p = LayerPipeline(tp, cam, cfg, match_camera=True, all_metrics=True)
    res = p.process(_frame(job).photo, LAYER)
    assert res.status == "ok"
    assert len(res.per_metric) == 12
    assert not np.array_equal(p.reference(LAYER).image, StackRenderer(tp, job[3], cfg.render).render(LAYER).image)


def test_disk_cache_reused(job, tmp_path):
    tp, cam, cfg, _ = job
    a = LayerPipeline(tp, cam, cfg, cache_dir=tmp_path).reference(3)
    assert any(tmp_path.rglob("*"))
    b = LayerPipeline(tp, cam, cfg, cache_dir=tmp_path).reference(3)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.footprint, b.footprint)


def test_frame_gate_hook_rejects_before_the_warp_and_sees_the_previous_frame(job):
    tp, cam, cfg, _ = job
    seen = []

    def gate(photo, previous, settings):
        seen.append((photo, previous, settings))
        return "too dark" if photo.mean() < 1 else None

    p = LayerPipeline(tp, cam, cfg, frame_gate=gate)
    good = _frame(job).photo
    assert p.process(good, LAYER).status == "ok"
    dark = np.zeros_like(good)
    res = p.process(dark, LAYER)
    assert res.status == "error" and res.message == "frame rejected: too dark" and "warp" not in res.timings_ms
    assert p.process(good, LAYER).status == "ok"
    assert seen[0][1] is None and seen[1][1] is good and seen[2][1] is good  # a rejected frame is not `previous`
    assert seen[0][2] is cfg.analysis
