"""The monitor never dies of its camera, and an unusable frame never counts toward a pause.

Each kind of camera fault (an exception of any type, ``None``, an empty array,
the wrong dtype or shape, a placeholder; and frames the camera-fault gate
refuses) is injected on a run of layers of a virtual print whose analysis
would pause on any analysed layer: the monitor records each faulty layer as
``camera_fault`` with its reason, alerts once after N in a row, records the
episode, resumes analysing when the camera recovers, and never pauses on a
fault.
"""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.frame_quality import FrameQualitySettings
from layerwatch.analysis.result import LayerResult, Region
from layerwatch.errors import CameraError
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.health import FaultSettings
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import CAMERA_FAULT, Monitor, frame_problem
from layerwatch.pipeline.policy import PausePolicy, PolicySettings
from layerwatch.storage.history import History

N_LAYERS = 12
FAULTY = range(4, 9)  # layers 4..8 get the fault


def _gcode(n: int = N_LAYERS) -> bytes:
    lines = []
    for i in range(n):
        z = 0.2 * (i + 1)
        lines += [f"G1 Z{z:.2f} F600", "G1 X10 Y10 E1", f"M118 E1 layerwatch snapshot layer={i} z={z:.2f}"]
    return "\n".join(lines).encode()


def _good(layer: int) -> np.ndarray:
    """A textured frame that changes with the layer (passes the gate)."""
    rng = np.random.default_rng(layer)
    y, x = np.mgrid[0:240, 0:320]
    img = 90 + 60 * np.sin(x / 9.0 + layer) * np.cos(y / 13.0) + rng.normal(0, 2, (240, 320))
    img[100:140, 140 + 3 * layer:180 + 3 * layer] = 230  # the "part" grows across the frame
    return np.repeat(np.clip(img, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


def _raise(exc):
    def f(layer):
        raise exc
    return f


#: kind -> what the camera does on a faulty layer (the SimCamera's frame function)
CAMERA_FAULTS = {
    "CameraError": _raise(CameraError("camera http://cam/snapshot unreachable (ConnectTimeout)")),
    "OSError": _raise(OSError(5, "Input/output error")),
    "RuntimeError": _raise(RuntimeError("driver crashed")),
    "ValueError": _raise(ValueError("bad frame")),
    "TimeoutError": _raise(TimeoutError()),
    "MemoryError": _raise(MemoryError()),
    "None": lambda layer: None,
    "empty": lambda layer: np.zeros((0, 0, 3), np.uint8),
    "float_dtype": lambda layer: _good(layer).astype(np.float64),
    "uint16_dtype": lambda layer: _good(layer).astype(np.uint16) * 256,
    "two_channel_shape": lambda layer: _good(layer)[:, :, :2],
    "5d_shape": lambda layer: _good(layer)[None, :, :, :, None],
    "1d": lambda layer: np.arange(100, dtype=np.uint8),
    "list": lambda layer: _good(layer).tolist(),
    "tiny": lambda layer: np.zeros((4, 4, 3), np.uint8),
}
#: faults only the gate sees (a valid array that shows no usable picture)
GATE_FAULTS = {
    "black": lambda layer: (_good(layer) * 0.03).astype(np.uint8),
    "over_exposed": lambda layer: np.clip(_good(layer).astype(np.int32) * 4 + 80, 0, 255).astype(np.uint8),
    "pure_noise": lambda layer: np.random.default_rng(layer).integers(0, 256, (240, 320, 3), dtype=np.uint8),
    "frozen_noisy": lambda layer: np.clip(_good(3).astype(np.float32)
                                          + np.random.default_rng(layer).normal(0, 2, (240, 320, 3)),
                                          0, 255).astype(np.uint8),
}


class PausingPipeline:
    """Reports a large failure on every layer it sees: any analysed fault frame would pause."""

    def __init__(self, from_layer: int = 10**6):
        self.seen: list[int] = []
        self.from_layer = from_layer

    def process(self, photo, layer_index):
        assert isinstance(photo, np.ndarray) and photo.dtype == np.uint8 and photo.ndim == 3
        self.seen.append(layer_index)
        bad = layer_index >= self.from_layer
        return LayerResult(layer=layer_index, z=0.2, anomaly_ratio=0.5 if bad else 0.0, printed_area_mm2=1000,
                           anomalous_area_mm2=500 if bad else 0, outside_area_mm2=400 if bad else 0,
                           regions=[Region(500, (0, 0, 20, 20), (10, 10), 20, 0.1, 0.0, 0.8)] if bad else [])


class Recorder:
    def __init__(self):
        self.sent = []

    def notify(self, title, message, *, level="warning", image=None, data=None, force=False):
        self.sent.append((level, message))
        return True


def _watch(kind_fn, gate: bool, wait: bool = True):
    frames = lambda layer: kind_fn(layer) if layer in FAULTY else _good(layer)  # noqa: E731
    pipe, rec, hist = PausingPipeline(), Recorder(), History(":memory:")
    job = hist.start_job("virtual", "part.gcode")
    mon = Monitor(VirtualPrinter(_gcode()), SimCamera(frames), pipe, PausePolicy(PolicySettings(skip_first_layers=0)),
                  notifier=rec, history=hist, job_id=job, wait_for_verdict=wait,
                  faults=FaultSettings(camera_alert_after=3),
                  frame_quality=FrameQualitySettings() if gate else None)
    rep = mon.run(poll_s=0.001)
    return rep, pipe, rec, [e["kind"] for e in hist.events(job)]


def _check_fault_run(rep, pipe, rec, events):
    assert rep.outcome == "done" and rep.pauses == 0
    assert [r.layer for r in rep.results] == list(range(N_LAYERS))
    faults = [r.layer for r in rep.results if r.status == CAMERA_FAULT]
    assert faults == list(FAULTY), [(r.layer, r.status, r.message) for r in rep.results]
    assert all(r.message for r in rep.results if r.status == CAMERA_FAULT)
    assert pipe.seen == [i for i in range(N_LAYERS) if i not in FAULTY]  # no fault frame analysed
    assert all(d.action == "none" for d in rep.decisions)  # never a pause, never a per-layer alert
    camera_alerts = [m for lvl, m in rec.sent if m.startswith("camera fault")]
    assert len(camera_alerts) == 1 and "3 unusable frames in a row" in camera_alerts[0]
    assert any(m.startswith("camera recovered") for _, m in rec.sent)
    assert events.count("camera_fault") == 1 and events.count("camera_recovered") == 1
    assert rep.camera_faults == len(FAULTY)


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(CAMERA_FAULTS))
def test_camera_faults_are_recorded_alerted_and_never_pause(kind):
    _check_fault_run(*_watch(CAMERA_FAULTS[kind], gate=False))


@pytest.mark.parametrize("kind", list(GATE_FAULTS))
def test_gate_refuses_unusable_frames(kind):
    _check_fault_run(*_watch(GATE_FAULTS[kind], gate=True))


def test_without_the_gate_a_black_frame_is_analysed():
    """The gate is what keeps such frames away from the pipeline (this test's pipeline pauses on none)."""
    rep, pipe, _, _ = _watch(GATE_FAULTS["black"], gate=False)
    assert pipe.seen == list(range(N_LAYERS)) and not any(r.status == CAMERA_FAULT for r in rep.results)


def test_camera_fault_records_keep_layer_order_when_not_waiting():
    rep, pipe, _, _ = _watch(CAMERA_FAULTS["RuntimeError"], gate=False, wait=False)
    assert [r.layer for r in rep.results] == list(range(N_LAYERS)) and rep.pauses == 0


def test_real_failure_still_pauses_with_the_gate_on():
    pipe = PausingPipeline(from_layer=6)
    mon = Monitor(VirtualPrinter(_gcode()), SimCamera(_good), pipe, PausePolicy(PolicySettings(skip_first_layers=0)),
                  wait_for_verdict=True, frame_quality=FrameQualitySettings())
    rep = mon.run(poll_s=0.001)
    assert rep.pauses == 1 and not any(r.status == CAMERA_FAULT for r in rep.results)


def test_frame_problem_names_each_defect():
    assert frame_problem(_good(1)) is None
    assert "NoneType" in frame_problem(None)
    assert "float64" in frame_problem(_good(1).astype(float))
    assert "shape" in frame_problem(np.zeros((20, 20, 4), np.uint8))
    assert "4x4" in frame_problem(np.zeros((4, 4, 3), np.uint8))


class HoldingPrinter(VirtualPrinter):
    """A virtual printer that records when the monitor ends each photo hold (Klipper's LAYERWATCH_SNAPSHOT)."""

    def __init__(self, gcode: bytes):
        super().__init__(gcode)
        self.released: list[int] = []

    def photo_done(self, trigger):
        self.released.append(trigger.layer)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["CameraError", "None"])
def test_every_hold_is_released_after_the_photo_also_when_the_camera_fails(kind):
    frames = lambda layer: CAMERA_FAULTS[kind](layer) if layer in FAULTY else _good(layer)  # noqa: E731
    printer = HoldingPrinter(_gcode())
    mon = Monitor(printer, SimCamera(frames), PausingPipeline(), PausePolicy(PolicySettings(skip_first_layers=0)),
                  wait_for_verdict=True)
    mon.run(poll_s=0.001)
    assert printer.released == list(range(N_LAYERS))  # one release per layer, in order, faults included


class BuggyPipeline(PausingPipeline):
    """A pipeline with a bug on layers 4 and 5 (raises as a coding error would, not a layer's error record)."""

    def process(self, photo, layer_index):
        if layer_index in (4, 5):
            self.seen.append(layer_index)
            raise TypeError("unsupported operand type(s) for +: 'NoneType' and 'int'")
        return super().process(photo, layer_index)


def test_a_pipeline_bug_is_recorded_and_the_monitor_goes_on_without_pausing():
    pipe, rec, hist = BuggyPipeline(), Recorder(), History(":memory:")
    job = hist.start_job("virtual", "part.gcode")
    mon = Monitor(VirtualPrinter(_gcode()), SimCamera(_good), pipe, PausePolicy(PolicySettings(skip_first_layers=0)),
                  notifier=rec, history=hist, job_id=job, faults=FaultSettings(camera_alert_after=3))
    rep = mon.run(poll_s=0.001)
    assert rep.outcome == "done" and rep.pauses == 0
    assert [r.layer for r in rep.results] == list(range(N_LAYERS))  # every layer after the bug analysed
    failed = [(r.layer, r.message) for r in rep.results if r.status == "error"]
    assert [layer for layer, _ in failed] == [4, 5] and all("NoneType" in m for _, m in failed)
    assert not any(d.stops for d in rep.decisions)  # an alert at most, never a pause
    assert any("pipeline failed" in m for _, m in rec.sent)  # the operator is told
