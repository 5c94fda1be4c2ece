"""The monitor's job-aware camera checks: a stream one layer late, and a camera that moved.

Lag: a small stand-in pipeline whose "photos" are already top views and whose
analysis is the real one (:func:`~layerwatch.analysis.scoring.analyze_layer`
against layer references whose printed shape changes every layer), so a frame
of layer ``k - 1`` delivered at layer ``k`` is a large anomaly against layer
``k``'s reference and pauses a clean print unless the lag check sees it.

Markers: a posed camera with four dot markers drawn where it projects them;
a bumped camera (the whole frame shifted) must become camera-fault records and
one alert, never an analysed layer; spaghetti over the markers must not.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from test_camera_faults import PausingPipeline, Recorder, _gcode, _good

from layerwatch.analysis.frame_quality import FrameQualitySettings
from layerwatch.analysis.result import LayerResult
from layerwatch.analysis.scoring import analyze_layer
from layerwatch.analysis.settings import AnalysisSettings
from layerwatch.geometry.markers import confirm_dots, detect_dots
from layerwatch.geometry.synthetic import project_points
from layerwatch.geometry.topview import TopView
from layerwatch.monitor.camera_checks import LagVerdict, LateStream, MarkerWatch, Progress
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.health import FaultSettings
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import CAMERA_FAULT, Monitor
from layerwatch.pipeline.config import MarkerSettings
from layerwatch.pipeline.policy import PausePolicy, PolicySettings
from layerwatch.pipeline.step import Reference
from layerwatch.simulate import default_camera

N_LAYERS = 12
TV = TopView(3.0, 60.0, 60.0, (0.0, 0.0))  # 180 x 180 px top view


def _layer_picture(layer: int, blob: bool = False, seed: int = 0, turns: frozenset[int] | None = None,
                   light: int | None = None, beads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Grey top view of the part after ``layer`` and its footprint.

    The part is a bar that grows by 1 mm a layer and turns by 90 degrees on every layer, its
    infill lines at +-45 degrees in turn; or (``turns``) a bar that turns only on the layers in
    ``turns``, grows by 1/3 mm a layer and whose infill lines move sideways from layer to layer.
    ``light``: a new exposure taken at that trigger (the light falls differently, new sensor
    noise), so a picture of an unchanged scene is no repeat for the gate. ``beads``: the infill
    lines moved sideways by that many px (new beads on the same shape).
    """
    h, w = TV.shape
    y, x = np.mgrid[0:h, 0:w]
    img = 70 + 25 * np.sin(x / 5.0) * np.cos(y / 7.0)  # the bed's texture
    foot = np.zeros((h, w), bool)
    long_side = 40 + (3 * layer if turns is None else layer)
    turned = layer % 2 if turns is None else sum(t <= layer for t in turns) % 2
    if layer < 0:  # the empty bed, before the first layer
        pass
    elif turned:
        foot[90 - long_side // 2:90 + long_side // 2, 70:110] = True
    else:
        foot[70:110, 90 - long_side // 2:90 + long_side // 2] = True
    lines = ((x + y if layer % 2 else x - y) if turns is None else x - y + 5 * layer) + beads
    stripes = 170 + 50 * np.sign(np.sin(lines / 2.0))  # infill lines
    img = np.where(foot, stripes, img)
    if blob:  # a dark clump of spaghetti on and beside the part
        cv2.circle(img, (120, 80), 18, 20, -1)
    if light is not None:  # a smooth fall-off of the light that moves from exposure to exposure
        img = img * (1.0 + 0.12 * np.cos(2 * np.pi * (x + 0.5 * y) / w + light))
    img = img + np.random.default_rng([max(layer, 0), seed, 0 if light is None else light + 1]).normal(0, 2, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8), foot


class TopViewPipeline:
    """A pipeline whose photos are top views already: the real HOG analysis against per-layer references."""

    def __init__(self, turns: frozenset[int] | None = None) -> None:
        self.topview = TV
        self.turns = turns
        self.config = SimpleNamespace(analysis=AnalysisSettings())
        self.seen: list[int] = []

    def reference(self, index: int) -> Reference:
        image, foot = _layer_picture(index, seed=99, turns=self.turns)
        return Reference(image, foot, 0.2 * (index + 1))

    def top_view(self, photo: np.ndarray, z: float, box=None) -> tuple[np.ndarray, np.ndarray]:
        top, valid = cv2.cvtColor(photo, cv2.COLOR_BGR2GRAY), np.ones(TV.shape, bool)
        return (top, valid) if box is None else (top[box], valid[box])

    def process(self, photo: np.ndarray, layer_index: int):
        self.seen.append(layer_index)
        ref = self.reference(layer_index)
        top, valid = self.top_view(photo, ref.z)
        return analyze_layer(top, ref.image, ref.footprint, TV, self.config.analysis, valid=valid,
                             layer=layer_index, z=ref.z)


def _photo(layer: int, blob: bool = False, turns: frozenset[int] | None = None, light: int | None = None,
           beads: int = 0) -> np.ndarray:
    return cv2.cvtColor(_layer_picture(layer, blob, turns=turns, light=light, beads=beads)[0], cv2.COLOR_GRAY2BGR)


def _lagged(from_layer: int = 1, blob_from: int | None = None, fresh: bool = False):
    """A camera one layer late from ``from_layer`` on (layer k gets the picture of layer k-1).

    ``fresh``: every picture is a new exposure (the first late one is then no repeat for the gate).
    """
    def frame(layer: int) -> np.ndarray:
        shown = layer - 1 if layer >= from_layer else layer
        return _photo(shown, blob=blob_from is not None and shown >= blob_from, light=layer if fresh else None)
    return frame


def _watch_lag(frames, gate: bool = True, turns: frozenset[int] | None = None, **quality):
    rec = Recorder()
    mon = Monitor(VirtualPrinter(_gcode(N_LAYERS)), SimCamera(frames), TopViewPipeline(turns),
                  PausePolicy(PolicySettings(skip_first_layers=1)), notifier=rec, wait_for_verdict=True,
                  faults=FaultSettings(camera_alert_after=3),
                  frame_quality=FrameQualitySettings(**quality) if gate else None)
    return mon.run(poll_s=0.001), rec


def test_the_stand_in_pipeline_sees_a_clean_print_clean_and_a_failure():
    rep, _ = _watch_lag(lambda layer: _photo(layer))
    assert rep.pauses == 0 and all(r.status == "ok" for r in rep.results)
    rep, _ = _watch_lag(lambda layer: _photo(layer, blob=layer >= 6))
    assert rep.pauses == 1


def _late(rep) -> list:
    """Results of frames the lag check found one layer late."""
    return [r for r in rep.results if "lag_area_mm2" in r.frame_quality]


def test_a_camera_one_layer_late_for_the_whole_print_never_pauses():
    rep_off, _ = _watch_lag(_lagged(), gate=False)
    assert rep_off.pauses == 1  # without the checks the late frames pause this clean print
    rep, rec = _watch_lag(_lagged())
    assert rep.pauses == 0 and rep.outcome == "done"
    faults = [r for r in rep.results if r.status == CAMERA_FAULT]
    assert [r.layer for r in faults] == [1] and "same picture" in faults[0].message  # layer 0's picture again
    late = _late(rep)
    assert [r.layer for r in late] == list(range(2, N_LAYERS)) and rep.lagged_frames == len(late)
    assert all(r.status == "ok" and "shows layer" in r.message and "one layer late" in r.message for r in late)
    assert all(r.frame_quality["lag_previous_area_mm2"] < r.frame_quality["lag_area_mm2"] for r in late)
    alerts = [m for _, m in rec.sent if m.startswith("camera")]
    assert len(alerts) == 1 and alerts[0].startswith("camera lagging: 3 frames")  # consistent: alerted once


def _excused(rep) -> list[int]:
    return [r.layer for r in _late(rep)]


def test_a_camera_that_falls_behind_at_layer_k_never_pauses_and_is_alerted():
    """The first late frame repeats the picture before it (a repeat, or a new exposure without progress)."""
    for fresh in (False, True):
        rep_off, _ = _watch_lag(_lagged(5, fresh=fresh), gate=False)
        assert rep_off.pauses == 1  # without the checks the late frames pause this clean print
        rep, rec = _watch_lag(_lagged(5, fresh=fresh))
        assert rep.pauses == 0 and rep.outcome == "done", fresh
        first = rep.results[5]  # the picture of layer 4 again
        if fresh:  # a new exposure without progress: taken as the slip, judged against layer 4
            assert first.status == "ok" and "the next frame tells" in first.message
        else:
            assert first.status == CAMERA_FAULT and "same picture" in first.message
        assert _excused(rep) == list(range(6 - fresh, N_LAYERS)), fresh
        assert all(r.frame_quality["lag_progress_changed"] > 0.5 for r in _late(rep) if r.layer > 5)
        alerts = [m for _, m in rec.sent if m.startswith("camera lagging")]
        assert len(alerts) == 1 and alerts[0].startswith("camera lagging: 3 frames"), alerts


def test_a_camera_late_from_the_job_start_never_pauses():
    """Layer 0 gets the empty bed: the first layer is not in the picture (the slip), layer 1 on are excused."""
    for fresh in (False, True):
        rep, rec = _watch_lag(_lagged(0, fresh=fresh))
        assert rep.pauses == 0 and rep.outcome == "done", fresh
        assert _excused(rep) == list(range(1, N_LAYERS)), (fresh, _excused(rep))
        assert len([m for _, m in rec.sent if m.startswith("camera lagging")]) == 1


def test_a_stalled_print_is_never_excused_and_pauses():
    """Nothing printed from layer 7 on: each frame is a new exposure of layer 6 (so the gate passes it)."""
    stall = 7
    rep, rec = _watch_lag(lambda layer: _photo(min(layer, stall - 1), light=layer))
    assert _excused(rep) == [stall]  # its first layer cannot be told from a camera that fell behind
    stops = [d.layer for d in rep.decisions if d.stops]
    assert rep.pauses == 1 and stops[0] in (stall + 1, stall + 2), stops
    assert "twice in a row" in rep.results[stops[0]].message
    assert not any(m.startswith("camera lagging") for _, m in rec.sent)


def test_a_stall_under_steady_light_is_a_repeat_alerted_as_a_possible_stall():
    """Frames that differ by sensor noise alone are repeats (a frozen camera gives the same pixels): a camera
    fault, never a pause, and the alert says the print may have stopped growing (docs/security.md, gaps)."""
    rep, rec = _watch_lag(lambda layer: _photo(min(layer, 6)))  # the same picture from layer 7 on
    assert rep.pauses == 0 and [r.layer for r in rep.results if r.status == CAMERA_FAULT] == list(range(7, N_LAYERS))
    alerts = [m for _, m in rec.sent if m.startswith("camera fault")]
    assert len(alerts) == 1 and "may have stopped growing" in alerts[0], alerts


def test_a_stalled_print_behind_a_late_camera_is_not_excused():
    """Late from layer 3, nothing printed from layer 7 on: the late frames stop showing progress."""
    stall = 7
    rep, _ = _watch_lag(lambda layer: _photo(min(layer - 1 if layer >= 3 else layer, stall - 1), light=layer))
    assert _excused(rep) == list(range(3, stall + 1))  # the slip at 3, then up to the last picture with progress
    stops = [d.layer for d in rep.decisions if d.stops]
    assert rep.pauses == 1 and stops[0] in (stall + 1, stall + 2), stops


def test_a_failure_on_time_that_looks_like_the_previous_layer_is_not_excused():
    """From layer 6 the part stops turning but new beads go on it: each frame looks like layer 5's reference
    and shows progress; the camera never slipped, so it is judged as it is."""
    def frame(layer: int) -> np.ndarray:
        return _photo(layer, light=layer) if layer < 6 else _photo(5, light=layer, beads=3 * (layer - 5))
    rep, _ = _watch_lag(frame)
    assert "the camera was on time so far" in rep.results[6].message and not _late(rep)
    stops = [d.layer for d in rep.decisions if d.stops]
    assert rep.pauses == 1 and stops[0] in (6, 7), stops


def test_late_stream_state():
    pipe, late = TopViewPipeline(), LateStream(after_n=2)
    res = LayerResult(layer=4, z=1.0, status="ok")
    lagged = LagVerdict(True, 50.0, 1.0, "late", res)
    moving, still = Progress(0.6, 40), Progress(0.0, 40)
    assert "on time so far" in late.excuse(lagged, moving, res)  # no slip yet
    assert late.excuse(lagged, still, res) is None  # the first frame without progress: taken as the slip
    assert "no earlier frame" in late.excuse(lagged, Progress(float("nan"), 0), res)
    late.interrupted()  # a refused frame: the stream may come back late
    assert late.excuse(lagged, moving, res) is None
    assert "twice in a row" in late.excuse(lagged, still, res)  # a stall, not a slip
    assert [late.excused(moving), late.excused(moving), late.excused(moving)] == [False, True, False]  # once
    assert "too little to tell" in late.excuse(lagged, Progress(0.1, 40), res)  # between still and printed
    late.judged(res, LagVerdict(False, 5.0, 9.0), moving)  # judged as it was, its own layer explained it better
    assert not late.slipped and not late.still and late.count == 0
    late.judged(res, LagVerdict(False, 9.0, 5.0), moving)  # not explained, not better by its own layer either
    assert not late.slipped
    late.judged(res, None, still)  # a frame without progress: slipped here
    assert late.slipped and "twice in a row" in late.excuse(lagged, still, res)
    res.failed_check = "nothing_extruded"
    assert "nothing-extruded check failed" in late.excuse(lagged, moving, res)
    # progress on the real top views: a new exposure of the same layer is still, the next layer is not
    late.remember(pipe, 4, pipe.top_view(_photo(4, light=1), 1.0)[0])
    p_same = late.progress(pipe, _photo(4, light=2), 5)
    p_next = late.progress(pipe, _photo(5, light=2), 5)
    assert p_same is not None and p_next is not None
    assert p_same.still and p_next.printed, (p_same, p_next)


def test_a_late_camera_is_alerted_when_its_frames_are_far_apart():
    """A late camera shows only where the part turns: the lag alert says so after 3 such layers."""
    turns = frozenset({3, 6, 9, 11})
    rep_off, _ = _watch_lag(lambda layer: _photo(max(layer - 1, 0), turns=turns), gate=False, turns=turns)
    assert sum(d.action == "notify" for d in rep_off.decisions) >= 3  # false failure alerts without the checks
    rep, rec = _watch_lag(lambda layer: _photo(max(layer - 1, 0), turns=turns), turns=turns)
    assert rep.pauses == 0 and all(d.action == "none" for d in rep.decisions)
    late = [r.layer for r in _late(rep)]
    assert len(late) >= 3 and all(b - a >= 2 for a, b in zip(late, late[1:], strict=False)), late  # far apart
    alerts = [m for _, m in rec.sent if m.startswith("camera")]
    assert len(alerts) == 1 and alerts[0].startswith("camera lagging: 3 frames"), alerts


def test_a_real_failure_still_pauses_through_a_late_camera_and_on_time():
    rep, _ = _watch_lag(_lagged(blob_from=6))  # late and failing: judged against the layer it shows
    stops = [d.layer for d in rep.decisions if d.stops]
    assert rep.pauses == 1 and stops[0] in (7, 8)
    assert "lag_area_mm2" in rep.results[stops[0]].frame_quality  # the pausing frame was a late one
    rep, _ = _watch_lag(lambda layer: _photo(layer, blob=layer >= 6))  # gate on, camera on time
    assert rep.pauses == 1 and not _late(rep) and not any(r.status == CAMERA_FAULT for r in rep.results)


# ---------------------------------------------------------------- markers
W, H = 480, 360
MARK_MM = np.array([[-40.0, -40.0], [40.0, -40.0], [40.0, 40.0], [-40.0, 40.0]])
CAMERA = dataclasses.replace(default_camera(TopView(3.0, 100, 100, (0, 0)), image_size=(W, H)),
                             markers_mm=MARK_MM)
MARKS_PX = project_points(CAMERA, MARK_MM)


def _marked(layer: int, shift: tuple[float, float] = (0.0, 0.0), spaghetti: bool = False) -> np.ndarray:
    """A frame with the four bed markers where the camera sees them (shifted when it was bumped)."""
    img = cv2.resize(_good(layer), (W, H))
    img = (img * 0.5).astype(np.uint8)  # a darker bed, white dots on it
    for u, v in MARKS_PX:
        cv2.circle(img, (round(u), round(v)), 7, (245, 245, 245), -1, lineType=cv2.LINE_AA)
    if spaghetti:  # strands over three of the markers and much of the picture
        rng = np.random.default_rng(layer)
        for u, v in MARKS_PX[:3]:
            for _ in range(12):
                p = (np.array([u, v]) + rng.normal(0, 14, 2)).astype(int)
                q = (np.array([u, v]) + rng.normal(0, 14, 2)).astype(int)
                cv2.line(img, tuple(int(c) for c in p), tuple(int(c) for c in q), (40, 30, 160), 4)
        for _ in range(60):
            p, q = rng.integers(0, [W, H], size=(2, 2))
            cv2.line(img, tuple(int(c) for c in p), tuple(int(c) for c in q), (40, 30, 160), 3)
    if shift != (0.0, 0.0):
        m = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
        img = cv2.warpAffine(img, m, (W, H), borderMode=cv2.BORDER_REPLICATE)
    return img


class MarkedPipeline(PausingPipeline):
    """PausingPipeline with a calibrated camera (marker positions) as LayerPipeline has."""

    def __init__(self, from_layer: int = 10**6):
        super().__init__(from_layer)
        self.camera = CAMERA
        self.config = SimpleNamespace(markers=MarkerSettings())


def _watch_markers(frames, pipe, counts=None):
    rec = Recorder()
    mon = Monitor(VirtualPrinter(_gcode(N_LAYERS)), SimCamera(frames), pipe,
                  PausePolicy(PolicySettings(skip_first_layers=0)), notifier=rec, wait_for_verdict=True,
                  faults=FaultSettings(camera_alert_after=3), frame_quality=FrameQualitySettings())
    rep = mon.run(poll_s=0.001)
    if counts is not None:  # frames whose markers were confirmed in place / fully detected
        counts.extend([mon.frame_checks.markers.confirmed, mon.frame_checks.markers.detected])
    return rep, rec


def test_marker_watch_finds_the_markers_where_the_calibration_puts_them():
    watch = MarkerWatch.of_pipeline(MarkedPipeline())
    assert watch is not None and MarkerWatch.of_pipeline(PausingPipeline()) is None
    found = watch(_marked(2))
    d = np.linalg.norm(found["expected_markers_px"][:, None] - found["markers_px"][None], axis=2).min(axis=1)
    assert np.all(d < 1.5)
    big = watch.expected_px((2 * W, 2 * H))  # at the frame's size
    assert np.allclose(big, 2 * found["expected_markers_px"], atol=0.5)


def test_a_bumped_camera_is_a_camera_fault_never_analysed_or_paused():
    bumped = range(5, N_LAYERS)
    pipe = MarkedPipeline(from_layer=5)  # any analysed frame from layer 5 on would pause
    counts: list[int] = []
    rep, rec = _watch_markers(lambda i: _marked(i, (24.0, -18.0) if i in bumped else (0.0, 0.0)), pipe, counts)
    assert rep.pauses == 0 and pipe.seen == list(range(5))
    assert counts == [4, N_LAYERS - 4]  # layers 1-4 confirmed in place; the first and every bumped frame in full
    faults = [r for r in rep.results if r.status == CAMERA_FAULT]
    assert [r.layer for r in faults] == list(bumped)
    assert all("camera moved" in r.message and r.frame_quality["marker_shift_px"] > 25 for r in faults)
    assert len([m for _, m in rec.sent if m.startswith("camera fault")]) == 1  # after 3 in a row, once


def test_spaghetti_over_the_markers_is_analysed_and_pauses():
    pipe = MarkedPipeline(from_layer=5)
    rep, _ = _watch_markers(lambda i: _marked(i, spaghetti=i >= 5), pipe)
    assert not any(r.status == CAMERA_FAULT for r in rep.results), [r.message for r in rep.results]
    assert rep.pauses == 1 and 5 in pipe.seen


def test_markers_in_place_are_confirmed_without_the_full_detection_and_a_bump_still_runs_it():
    watch = MarkerWatch.of_pipeline(MarkedPipeline(), 12.0)
    full = MarkerWatch.of_pipeline(MarkedPipeline())  # confirm_px 0: always the full detection
    assert watch is not None and full is not None
    first = watch(_marked(1))
    assert (watch.detected, watch.confirmed) == (1, 0)  # the first frame learns the dots' areas
    for layer in (2, 3):
        got, ref = watch(_marked(layer)), full(_marked(layer))
        d = np.linalg.norm(ref["markers_px"][:, None] - got["markers_px"][None], axis=2).min(axis=0)
        assert len(got["markers_px"]) == 4 and np.all(d < 0.5)  # the same dots, refined the same way
    assert (watch.detected, watch.confirmed) == (1, 2) and full.confirmed == 0
    bumped = watch(_marked(4, (24.0, -18.0)))  # nothing in place: the full detection, as without confirmation
    assert watch.detected == 2
    assert np.allclose(bumped["markers_px"], full(_marked(4, (24.0, -18.0)))["markers_px"])
    assert first["expected_markers_px"] is bumped["expected_markers_px"]


def test_confirm_dots_refuses_dots_off_their_place_or_of_another_size():
    img = _marked(2)
    area = np.median([b.area for b in detect_dots(img)])
    areas = np.full(4, area)
    assert np.isfinite(confirm_dots(img, MARKS_PX, areas, 3.0)).all()
    assert np.isnan(confirm_dots(img, MARKS_PX + [5.0, 0.0], areas, 3.0)).all()  # 5 px away: not confirmed
    assert np.isnan(confirm_dots(img, MARKS_PX, areas * 4, 3.0)).all()  # a dot a quarter of the size learned
    unknown = confirm_dots(img, np.vstack([MARKS_PX, [[-50.0, 10.0]]]), np.append([np.nan, *areas[1:]], area), 3.0)
    assert np.isnan(unknown[[0, 4]]).all() and np.isfinite(unknown[1:4]).all()  # no area, outside the frame


def _refine_before(grey, box):
    """geometry.markers._refine as it was written with numpy's median, percentile and full grids (the reference)."""
    x, y, w, h = box
    H, W = grey.shape
    pad = max(3, int(0.6 * max(w, h)))
    x0, y0, x1, y1 = max(x - pad, 0), max(y - pad, 0), min(x + w + pad, W), min(y + h + pad, H)
    roi = grey[y0:y1, x0:x1].astype(np.float32)
    border = np.concatenate([roi[0], roi[-1], roi[:, 0], roi[:, -1]])
    bg = float(np.median(border))
    peak = float(np.percentile(roi, 99.5))
    if peak - bg < 20:
        return None
    cov = np.clip((roi - bg) / (peak - bg) * 1.15 - 0.075, 0.0, 1.0)
    n, lab = cv2.connectedComponents((cov > 0.5).astype(np.uint8))
    if n < 2:
        return None
    cy, cx = (y + h / 2 - y0), (x + w / 2 - x0)
    yy, xx = np.nonzero(lab)
    k = lab[yy, xx][np.argmin((yy - cy) ** 2 + (xx - cx) ** 2)]
    keep = cv2.dilate((lab == k).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    cov = np.where(keep, cov, 0.0)
    s = float(cov.sum())
    if s <= 0:
        return None
    gy, gx = np.mgrid[0 : roi.shape[0], 0 : roi.shape[1]]
    return float((cov * gx).sum() / s + x0), float((cov * gy).sum() / s + y0), s


def test_marker_refinement_gives_the_figures_of_numpys_median_percentile_and_grids_bit_for_bit():
    from layerwatch.geometry import markers

    rng = np.random.default_rng(5)
    grey = cv2.cvtColor(_marked(2), cv2.COLOR_BGR2GRAY)
    noisy = np.clip(grey + rng.normal(0, 6, grey.shape), 0, 255).astype(np.uint8)
    H, W = grey.shape
    found = 0
    for img in (grey, noisy):
        boxes = [(int(u) - 12 + int(rng.integers(-6, 7)), int(v) - 12 + int(rng.integers(-6, 7)), 24, 24)
                 for u, v in MARKS_PX for _ in range(10)]
        boxes += [(int(rng.integers(-20, W)), int(rng.integers(-20, H)), int(rng.integers(1, 60)), int(rng.integers(1, 60)))
                  for _ in range(200)]  # anywhere, edges and corners too, odd and even sizes
        for box in boxes:
            got, want = markers._refine(img, box), _refine_before(img, box)
            assert got == want, box
            found += got is not None
    assert found >= 80  # most boxes on a dot refine one
    values = rng.integers(0, 256, 1001).astype(np.uint8)
    for n in (1, 2, 3, 7, 8, 200, 1001):
        for q in (0.0, 1.0, 50.0, 99.5, 99.9, 100.0):
            assert markers._percentile(values[:n], q) == float(np.percentile(values[:n].astype(np.float32), q))
        assert markers._median(values[:n]) == float(np.median(values[:n].astype(np.float32)))


def test_the_nearest_labelled_pixel_is_the_whole_images_argmin_ties_and_edges_included():
    """``markers._nearest_label`` (a growing window) picks the label numpy's argmin over every labelled pixel
    picks: sparse and dense label maps, points on pixels, between them (halves: exact ties), outside the map."""
    from layerwatch.geometry.markers import _nearest_label

    rng = np.random.default_rng(8)
    for trial in range(300):
        h, w = int(rng.integers(1, 90)), int(rng.integers(1, 90))
        lab = np.where(rng.random((h, w)) < rng.choice([0.002, 0.02, 0.3]), rng.integers(1, 5, (h, w)), 0)
        if not lab.any():
            lab[int(rng.integers(h)), int(rng.integers(w))] = 7
        cy, cx = rng.integers(-30, h + 30) / 2 * rng.choice([1, 2]), rng.integers(-30, w + 30) / 2 * rng.choice([1, 2])
        yy, xx = np.nonzero(lab)
        want = lab[yy, xx][np.argmin((yy - cy) ** 2 + (xx - cx) ** 2)]
        assert _nearest_label(lab, cy, cx) == want, (trial, cy, cx)
    ring = np.zeros((41, 41), np.int32)  # four pixels at one distance from the centre: the first row-major wins
    ring[20, 0], ring[0, 20], ring[40, 20], ring[20, 40] = 4, 3, 2, 1
    assert _nearest_label(ring, 20.0, 20.0) == 3
    with pytest.raises(ValueError):
        _nearest_label(np.zeros((5, 5), np.int32), 2.0, 2.0)


def test_ranked_u8_gives_the_partitions_values():
    from layerwatch.percentile import ranked_u8

    rng = np.random.default_rng(9)
    for n in (1, 2, 5, 256, 4001):
        values = rng.integers(0, rng.integers(1, 257), (n,)).astype(np.uint8)
        ranks = sorted({0, n // 2, n - 1, int(rng.integers(n))})
        assert np.array_equal(ranked_u8(values, ranks), np.partition(values, ranks)[ranks])
    with pytest.raises(ValueError):
        ranked_u8(np.zeros(4, np.float32), [0])
    with pytest.raises(ValueError):
        ranked_u8(np.zeros(4, np.uint8), [4])


def test_marker_watch_refuses_a_bad_confirm_distance():
    with pytest.raises(ValueError, match="confirm_px"):
        MarkerWatch(CAMERA, confirm_px=-1.0)
    with pytest.raises(ValueError, match="confirm_px"):
        MarkerWatch(CAMERA, confirm_px=float("nan"))


def test_a_layer_the_policy_can_alarm_on_reaches_the_lag_check_whatever_s_a_counts():
    """With ``anomalous_area = "printed"`` S_A leaves the tiles' share beside the part out; the policy's
    minimum-area test adds it back (``uncounted_mm2``), so the lag check must see the same sum."""
    from layerwatch.monitor.camera_checks import counts_toward_pause
    from layerwatch.pipeline.policy import PolicySettings

    policy = PolicySettings(min_area_mm2=5.0, skip_first_layers=0)
    printed_share = LayerResult(layer=4, z=1.0, status="ok", anomalous_area_mm2=3.0, uncounted_mm2=4.0)
    assert counts_toward_pause(printed_share, policy)
    assert not counts_toward_pause(dataclasses.replace(printed_share, uncounted_mm2=1.0), policy)


def test_the_progress_zone_dilated_on_the_footprints_box_is_the_whole_dilation():
    from layerwatch.monitor import camera_checks as cc
    tv = SimpleNamespace(px_per_mm=6.67)
    r = max(1, round(cc.PROGRESS_MARGIN_MM * tv.px_per_mm))
    rng = np.random.default_rng(0)
    for _ in range(200):
        fp = np.zeros((int(rng.integers(10, 120)), int(rng.integers(10, 120))), bool)
        for _ in range(int(rng.integers(0, 4))):
            y, x = rng.integers(0, fp.shape[0]), rng.integers(0, fp.shape[1])
            fp[y:y + rng.integers(1, 30), x:x + rng.integers(1, 30)] = True  # at the edges too
        want = cv2.dilate(fp.astype(np.uint8), cc._disk(r)).astype(bool)
        assert np.array_equal(cc._zone(fp, tv), want)
