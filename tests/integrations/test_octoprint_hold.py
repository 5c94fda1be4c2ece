"""The plugin's hold and settings logic without OctoPrint (its helpers do not import it)."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "integrations" / "octoprint"))

from octoprint_layerwatch.hold import SnapshotHold  # noqa: E402
from octoprint_layerwatch.job import BytesCamera, _HeldCamera  # noqa: E402
from octoprint_layerwatch.options import DEFAULTS, validate_options  # noqa: E402

from layerwatch.errors import CameraError, ConfigError  # noqa: E402


class Queue:
    """Stands for OctoPrint's job-on-hold flag: records every change with its time."""

    def __init__(self, refuse: bool = False) -> None:
        self.calls: list[tuple[bool, float]] = []
        self.refuse = refuse

    def __call__(self, on: bool) -> bool:
        self.calls.append((on, time.monotonic()))
        return not (on and self.refuse)


def _wait(rec, s=5.0):
    end = time.monotonic() + s
    while rec.outcome == "pending" and time.monotonic() < end:
        time.sleep(0.01)
    return rec


def test_hold_is_lifted_when_the_frame_is_in():
    q = Queue()
    rec = _wait(SnapshotHold(q, lambda t, expired: time.sleep(0.3), timeout_s=5).trigger(SimpleNamespace(layer=4)))
    assert rec.outcome == "frame" and rec.held and 290 <= rec.held_ms < 2000
    (on, t_on), (off, t_off) = q.calls
    assert on and not off and t_off - t_on >= 0.29


def test_dead_camera_hold_times_out_and_next_layer_is_skipped_not_held():
    q, stuck = Queue(), threading.Event()
    seen_expired = []

    def take(trigger, expired):
        stuck.wait(3)
        seen_expired.append(expired())

    hold = SnapshotHold(q, take, timeout_s=0.5)
    rec = _wait(hold.trigger(SimpleNamespace(layer=0)))
    assert rec.outcome == "timeout" and 500 <= rec.held_ms < 1500 and [c[0] for c in q.calls] == [True, False]
    second = hold.trigger(SimpleNamespace(layer=1))  # the camera is still stuck on layer 0
    assert second.outcome == "skipped" and not second.held and len(q.calls) == 2
    stuck.set()
    time.sleep(0.2)
    assert seen_expired == [True]  # the late frame is known to be late
    assert _wait(hold.trigger(SimpleNamespace(layer=2))).outcome == "frame"
    assert [r["outcome"] for r in hold.records()] == ["timeout", "skipped", "frame"]


def test_hold_refused_by_octoprint_still_takes_the_photo_and_never_lifts_a_foreign_hold():
    q, taken = Queue(refuse=True), []
    rec = _wait(SnapshotHold(q, lambda t, e: taken.append(t.layer), timeout_s=1).trigger(SimpleNamespace(layer=7)))
    assert taken == [7] and not rec.held and [c[0] for c in q.calls] == [True]


def test_end_of_print_lifts_a_pending_hold():
    q, gate = Queue(), threading.Event()
    hold = SnapshotHold(q, lambda t, e: gate.wait(3), timeout_s=30)
    rec = hold.trigger(SimpleNamespace(layer=0))
    hold.end()
    assert rec.outcome == "ended" and [c[0] for c in q.calls] == [True, False]
    gate.set()


def test_hold_timeout_must_be_finite():
    for bad in (0, -1, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            SnapshotHold(Queue(), lambda t, e: None, timeout_s=bad)


def test_frame_after_the_hold_timed_out_is_a_camera_fault():
    pngs = iter([cv2.imencode(".png", np.full((40, 60, 3), v, np.uint8))[1].tobytes() for v in (100, 150)])
    cam = _HeldCamera(BytesCamera(lambda: next(pngs), "test webcam"))
    assert cam.grab().shape == (40, 60, 3)
    cam.expired = lambda: True
    with pytest.raises(CameraError, match="after the hold timed out"):
        cam.grab()
    with pytest.raises(CameraError, match="test webcam failed"):
        BytesCamera(lambda: (_ for _ in ()).throw(TimeoutError("read timed out")), "test webcam").grab()


def test_settings_are_validated(tmp_path):
    model = tmp_path / "camera.toml"
    model.write_text("")
    ok = validate_options({"camera_model": str(model), "pause_ratio": "0.2", "consecutive_layers": "3"})
    assert ok["pause_ratio"] == 0.2 and ok["consecutive_layers"] == 3 and ok["hold_timeout_s"] == DEFAULTS["hold_timeout_s"]
    for bad, words in [({"camera_model": "camera.toml"}, "absolute"), ({"camera_model": str(tmp_path / "no.toml")}, "does not exist"),
                       ({"hold_timeout_s": "nan"}, "hold_timeout_s"), ({"hold_timeout_s": 0}, "hold_timeout_s"),
                       ({"pause_ratio": 7}, "pause_ratio"), ({"threshold": "inf"}, "threshold"),
                       ({"action": "explode"}, "action"), ({"camera": "sim"}, "camera"), ({"bogus": 1}, "bogus")]:
        with pytest.raises(ConfigError, match=words):
            validate_options(bad)
