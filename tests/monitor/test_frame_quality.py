"""The camera-fault gate (layerwatch.analysis.frame_quality): unit checks, real photos, and the simulator measurement."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

from layerwatch.analysis.frame_quality import (
    _NOISE_KERNEL,
    FrameQualitySettings,
    assess_frame,
    blockiness,
    compact_previous,
    marker_shift_px,
    noise_sigma,
)

PHOTOS = Path("/work/shared/data/photos")
BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "frame_quality_gate.py"


def _scene(layer: int = 0, noise: float = 2.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:360, 0:480]
    img = 100 + 50 * np.sin(x / 11.0) * np.cos(y / 7.0) + rng.normal(0, noise, (360, 480))
    img[150:200, 200:200 + 10 * (layer + 1)] = 220  # the part grows with each layer
    return np.repeat(np.clip(img, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


def _jpeg(img, q):
    return cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, q])[1], cv2.IMREAD_COLOR)


def test_a_good_frame_passes_with_its_figures():
    q = assess_frame(_scene(1), _scene(0, seed=1))
    assert q.ok and not q.reasons
    assert {"p1", "p99", "noise", "blockiness", "sharpness", "change"} <= set(q.figures)


@pytest.mark.parametrize("kind, frame, reason", [
    ("black", (_scene() * 0.03).astype(np.uint8), "black frame"),
    ("white", np.clip(_scene().astype(int) * 4 + 80, 0, 255).astype(np.uint8), "over-exposed"),
    ("flat", np.full((360, 480, 3), 128, np.uint8), "no dynamic range"),
    ("noise", np.random.default_rng(0).integers(0, 256, (360, 480, 3), dtype=np.uint8), "noise"),
    ("jpeg5", _jpeg(_scene(), 5), "JPEG blocking"),
])
def test_each_camera_fault_is_named(kind, frame, reason):
    q = assess_frame(frame)
    assert not q.ok and any(reason in r for r in q.reasons), (kind, q)


def test_a_repeated_frame_fails_even_with_fresh_noise_and_new_exposure_gain():
    prev = _scene(3, seed=1)
    again = np.clip(_scene(3, seed=2).astype(np.float32) * 1.05 + 4, 0, 255).astype(np.uint8)
    q = assess_frame(_jpeg(again, 80), [_scene(2), prev])
    assert not q.ok and "previous frame" in q.reasons[0]
    assert assess_frame(_scene(4, seed=2), prev).ok  # the next layer is new


def test_spaghetti_in_front_of_the_camera_passes():
    img = _scene(2)
    rng = np.random.default_rng(3)
    for _ in range(150):  # strands over most of the picture
        p = rng.integers(0, [480, 360], size=(2, 2))
        cv2.line(img, tuple(int(v) for v in p[0]), tuple(int(v) for v in p[1]), (30, 30, 200), 3)
    assert assess_frame(img, _scene(1)).ok


def test_marker_shift():
    expected = np.array([[10, 10], [400, 10], [400, 300], [10, 300]], float)
    assert marker_shift_px(expected + 1, expected, 50) == pytest.approx(np.sqrt(2))
    assert marker_shift_px(expected[:1] + 1, expected, 50) is None  # one marker (others hidden): no verdict
    q = assess_frame(_scene(), markers_px=expected + 30, expected_markers_px=expected)
    assert not q.ok and "camera moved" in q.reasons[0]
    assert assess_frame(_scene(), markers_px=expected[:1], expected_markers_px=expected).ok


def test_bad_input_is_a_value_error():
    with pytest.raises(ValueError, match="uint8"):
        assess_frame(np.zeros((10, 10, 3), np.float32))


def test_settings_are_bounded():
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        FrameQualitySettings(max_noise=float("inf"))
    with pytest.raises(ValidationError):
        FrameQualitySettings(max_blockiness=1.0)


@pytest.mark.skipif(not PHOTOS.is_dir(), reason="no real photos in /work/shared/data/photos")
def test_real_photos_pass():
    photos = sorted(PHOTOS.glob("*.jp*g"))
    refused = [(p.name, assess_frame(cv2.imread(str(p))).reasons) for p in photos]
    refused = [r for r in refused if r[1]]
    assert photos and not refused


@pytest.mark.slow
def test_simulator_measurement():
    """Issue 19's targets on the simulator with the default gate: 0 pauses from camera faults (a camera one
    layer late, as repeats or as new exposures, for a stretch or the whole print, and a bumped one), real
    failures still pause (a stall and spaghetti, on time and behind a late camera), >= 0.97 of failure
    frames pass the monitor's camera-fault checks.

    A smaller run of ``benchmarks/frame_quality_gate.py`` (the figures it prints are the benchmark's):
    120 planned failure frames instead of 240, and without the ``excuse_late_frames = false`` runs
    (the old default, a baseline the benchmark prints and nothing here asserts)."""
    spec = importlib.util.spec_from_file_location("frame_quality_gate", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    cfg, tp, truth, pipe, gcode, frames, bed = bench._job()
    extra = bench.fresh_faults(tp, truth, cfg.topview.topview())
    rows = bench.clean_print_pauses(cfg, pipe, gcode, frames, bed, extra=extra, excuse_off=False)
    assert {"lagging_stream", "lagging_stream_fresh", "late_from_10_fresh", "bumped", "lagged_whole_print",
            "lagged_whole_print_fresh", "bumped_whole_print"} <= set(rows)
    for kind, r in rows.items():
        assert r["pauses_gate_on"] == 0 and r["refused"] + r["lagged"] >= 1 and r["refused_clean"] == 0, (kind, r)
    for kind in ("lagged_whole_print", "lagged_whole_print_fresh", "bumped_whole_print"):
        assert rows[kind]["alerts"] >= 1, (kind, rows[kind])  # a fault that lasts the whole print is said
    # without the gate a bumped camera pauses; a camera one layer late for the whole print paused too until c4b8200
    # (session 22: the scene's first photo now brings the body of the layers it is said to show), and no longer
    assert rows["bumped_whole_print"]["pauses_gate_off"] >= 1, rows["bumped_whole_print"]
    assert sum(r["pauses_gate_off"] for r in rows.values()) >= 5  # the faults do pause without the gate
    for name, (pauses, stop, seen) in bench.failure_pauses(cfg, tp, truth, pipe, gcode, bed).items():
        assert pauses == 1 and stop is not None and seen <= stop <= seen + 2, (name, pauses, stop)
    res = bench.failure_frames_passed(tp, truth, cfg, pipe)
    total = sum(res["total"].values())
    assert len(res["total"]) >= 5 and sum(res["passed"].values()) / total >= 0.97
    assert sum(res["passed_slipped"].values()) / total >= 0.97  # even as if the camera had just slipped
    assert res["checked"] >= 10  # the previous layer's reference did judge failure frames (and let them through)


def test_noise_and_blockiness_are_their_definitions_on_uint8_frames():
    """The histogram median and the integer step sums give the figures of the plain formulas."""
    rng = np.random.default_rng(3)
    for shape in ((1080, 1920), (31, 47), (30, 47), (6, 7)):
        g = cv2.GaussianBlur(rng.integers(0, 256, shape, dtype=np.uint8), (0, 0), 1.2)
        resp = cv2.filter2D(g.astype(np.float32), -1, _NOISE_KERNEL)[1:-1, 1:-1]
        assert noise_sigma(g) == float(np.median(np.abs(resp)) / 0.6745 / 6.0)
        f = g.astype(np.float64)
        ratios = []
        for d in (np.abs(np.diff(f, axis=1)), np.abs(np.diff(f, axis=0)).T):
            n = d.shape[1] // 8 * 8
            if n < 16:
                ratios = [1.0]
                break
            per = d[:, :n].reshape(d.shape[0], -1, 8).mean(axis=(0, 1))
            ratios.append((per[7] + 0.5) / (np.delete(per, 7).mean() + 0.5))
        assert blockiness(g) == pytest.approx(float(np.mean(ratios)), rel=1e-12)


def test_the_noise_response_of_two_separable_passes_is_the_3x3_kernels():
    """noise_sigma's two 3-tap passes give the 3 x 3 kernel's integer response everywhere, extremes included."""
    from layerwatch.analysis.frame_quality import _NOISE_ROW

    rng = np.random.default_rng(11)
    checker = (np.indices((64, 96)).sum(axis=0) % 2 * 255).astype(np.uint8)  # |response| 2040, the largest
    for g in (checker, rng.integers(0, 256, (1080, 1920), dtype=np.uint8), rng.choice([0, 255], (37, 53)).astype(np.uint8)):
        want = cv2.filter2D(g.astype(np.float32), -1, _NOISE_KERNEL)[1:-1, 1:-1]
        got = cv2.sepFilter2D(g, cv2.CV_16S, _NOISE_ROW, _NOISE_ROW)[1:-1, 1:-1]
        assert np.array_equal(got, want)
    assert np.abs(cv2.filter2D(checker.astype(np.float32), -1, _NOISE_KERNEL)).max() == 2040


def test_noise_of_a_pure_noise_frame_is_its_definition_past_the_histogram_of_small_responses():
    """A median |response| of 255 or more (pure noise) is read from the full histogram: the same figure."""
    g = np.random.default_rng(5).integers(0, 256, (240, 320), dtype=np.uint8)
    resp = cv2.filter2D(g.astype(np.float32), -1, _NOISE_KERNEL)[1:-1, 1:-1]
    assert np.median(np.abs(resp)) > 255
    assert noise_sigma(g) == float(np.median(np.abs(resp)) / 0.6745 / 6.0)


def test_a_frame_reduced_by_the_caller_is_judged_as_the_frame_itself():
    """``small`` (the caller's compact_previous of the frame) gives the figures the gate computes itself."""
    rng = np.random.default_rng(8)
    frame = cv2.GaussianBlur(rng.integers(0, 256, (360, 1280, 3), dtype=np.uint8), (0, 0), 2.0)
    prev = compact_previous(cv2.GaussianBlur(rng.integers(0, 256, (360, 1280, 3), dtype=np.uint8), (0, 0), 2.0))
    own = assess_frame(frame, prev)
    given = assess_frame(frame, prev, small=compact_previous(frame))
    assert given.figures == own.figures and given.reasons == own.reasons and "change" in own.figures
    with pytest.raises(ValueError, match="compact_previous"):
        assess_frame(frame, prev, small=prev[:, :-1])


def test_change_from_figures_are_the_copying_statistics_and_polyfits_line():
    """change_from partitions its temporaries in place and fits the gain in closed form: the figures equal NumPy's
    median/percentile on copies after ``np.polyfit``'s line, up to the fit's rounding (~1e-13)."""
    import cv2

    from layerwatch.analysis.frame_quality import change_from

    rng = np.random.default_rng(11)
    for k in range(6):
        prev = rng.integers(0, 256, (90 + k, 160)).astype(np.float32)
        small = np.clip(prev * (0.9 + 0.05 * k) + rng.normal(0, 2 + k, prev.shape), 0, 255).astype(np.float32)
        a, b = np.polyfit(prev.ravel()[::7], small.ravel()[::7], 1)
        resid = cv2.blur(small - (a * prev + b), (5, 5))
        dev = np.abs(resid - float(np.median(resid)))
        spread = float(np.median(dev) / 0.6745)
        want = (float(max(np.percentile(dev, 99.9) - 3.0 * spread, 0.0)), spread)
        assert change_from(small, prev) == pytest.approx(want, rel=1e-9, abs=1e-9)


def test_the_closed_form_gain_fit_is_polyfits_line():
    from layerwatch.analysis.frame_quality import gain_fit

    rng = np.random.default_rng(3)
    for k in range(20):
        x = rng.integers(0, 256, 5000 + 37 * k).astype(np.float32)
        y = np.clip(x * rng.uniform(0.5, 1.5) + rng.uniform(-40, 40) + rng.normal(0, 1 + k, x.shape), 0, 255)
        y = y.astype(np.float32)
        a, b = np.polyfit(x, y, 1)
        got = gain_fit(x, y)
        assert abs(got[0] - a) < 1e-12 and abs(got[1] - b) < 1e-9
    flat = np.full(100, 7.0, np.float32)  # no line through a constant x: polyfit's answer
    with pytest.warns(np.exceptions.RankWarning):
        want = np.polyfit(flat, np.arange(100.0), 1)
    with pytest.warns(np.exceptions.RankWarning):
        assert gain_fit(flat, np.arange(100.0)) == (want[0], want[1])


@pytest.mark.parametrize("kind", ["scene", "black", "white", "flat", "real"])
def test_exposure_figures_from_the_histogram_are_numpys_percentiles(kind):
    """The gate reads p1, p99 and the white share from the reduced frame's 256-bin histogram: the figures
    numpy's percentile and mean give on the float32 frame (the path a caller's float32 ``small`` takes)."""
    frames = {"scene": _scene(2), "black": (_scene() * 0.03).astype(np.uint8),
              "white": np.clip(_scene().astype(int) * 4 + 80, 0, 255).astype(np.uint8),
              "flat": np.full((360, 480, 3), 128, np.uint8)}
    if kind == "real":
        photos = sorted(PHOTOS.glob("*.jp*g"))
        if not photos:
            pytest.skip("no real photos in ../shared")
        frame = cv2.imread(str(photos[0]), cv2.IMREAD_COLOR)
    else:
        frame = frames[kind]
    small = compact_previous(frame)
    hist = assess_frame(frame, small=small).figures
    sorted_ = assess_frame(frame, small=small.astype(np.float32)).figures  # no uint8: numpy's percentile
    assert assess_frame(frame).figures == hist
    for key in ("p1", "p99", "bright"):
        assert hist[key] == sorted_[key], key


def test_median_and_percentile_from_one_partition_are_numpys():
    from layerwatch.analysis.frame_quality import _median_and_percentile

    rng = np.random.default_rng(12)
    for n in (1, 2, 3, 1000, 1001, 230400):
        for v in (rng.normal(0, 2, n), np.abs(rng.standard_cauchy(n)), rng.integers(0, 4, n).astype(np.float64)):
            for q in (99.9, 50.0, 0.0, 100.0):
                assert _median_and_percentile(v.copy(), q) == (float(np.median(v)), float(np.percentile(v, q)))


def test_a_region_of_interest_without_pixels_is_refused_in_one_line():
    """The box is the caller's (``FrameChecks.roi`` from :func:`~layerwatch.geometry.roi.bed_roi`): an empty one is a
    bug there, refused with the frame's size named, never a gate verdict on no pixels."""
    grey = _scene().astype(np.uint8)
    with pytest.raises(ValueError, match=r"holds no pixel of the 480x360 frame"):
        assess_frame(grey, box=(slice(0, 0), slice(0, 100)))
    assert assess_frame(grey, box=(slice(48, 336), slice(48, 432))).figures["noise"] > 0
