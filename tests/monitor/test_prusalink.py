"""The PrusaLink connector against a fake PrusaLink that speaks the v1 API behind real digest auth.

Covers the control commands (and the 409 of a command in the wrong state), refused credentials,
layer changes from the polled Z (a Z-hop does not count), the camera snapshot, URL and key
validation, every kind of bad status reply as one :class:`PrinterError`, and a monitor that
lives through those faults and analyses the next layer.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from fake_prusalink import FAULTS, FakePrusaLink
from typer.testing import CliRunner

from layerwatch.analysis.result import LayerResult
from layerwatch.cli import app
from layerwatch.cli.monitor import open_printer
from layerwatch.errors import CameraError, ConfigError, PrinterError
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.follow import CameraSpec
from layerwatch.monitor.health import FaultSettings
from layerwatch.monitor.hosts import printer_camera
from layerwatch.monitor.printers.prusalink import PrusaLinkPrinter, ZLayerTracker, prusalink_target
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.storage.history import History


@pytest.fixture
def fake():
    f = FakePrusaLink()
    yield f
    f.close()


def _printer(fake, **kw):
    return PrusaLinkPrinter(fake.url, fake.password, timeout_s=kw.pop("timeout_s", 0.5), **kw)


def test_status_and_commands_through_digest_auth(fake):
    with _printer(fake) as p:
        st = p.status()
        assert (st.state, st.file, st.progress, st.z) == ("printing", "part.bgcode", pytest.approx(0.1), 0.2)
        p.pause()
        assert fake.state == "PAUSED" and p.status().state == "paused"
        with pytest.raises(PrinterError, match="409.*not in a state"):
            p.pause()
        p.resume()
        assert fake.state == "PRINTING"
        p.cancel()
        assert fake.state == "STOPPED" and p.status().state == "cancelled"
    assert fake.refused >= 1  # the client answered a digest challenge; nothing went through unauthenticated
    assert ("PUT", "/api/v1/job/7/pause") in fake.requests and ("DELETE", "/api/v1/job/7") in fake.requests


def test_wrong_password_is_one_line_naming_the_fix(fake):
    with PrusaLinkPrinter(fake.url, "wrong", timeout_s=0.5) as p, pytest.raises(PrinterError) as err:
        p.status()
    assert "refused the user and password (HTTP 401" in str(err.value) and "Settings > Network" in str(err.value)
    assert fake.requests == []


def test_no_job_to_act_on(fake):
    fake.job_id, fake.state = None, "IDLE"
    with _printer(fake) as p:
        assert p.status().state == "idle" and p.status().file is None
        with pytest.raises(PrinterError, match="no job to act on"):
            p.pause()


def test_layer_triggers_from_polled_z(fake):
    with _printer(fake, confirm_polls=2) as p:
        heights = [0.2, 0.2, 0.4, 0.4, 0.6, 0.6, 1.0, 0.6, 0.8, 0.8, 1.0, 1.0]  # 1.0 once: a Z-hop
        for z in heights:
            fake.z = z
            p.status()
        trig = p.poll_triggers()
        assert [(t.layer, t.z) for t in trig] == [(0, 0.2), (1, 0.4), (2, 0.6), (3, 0.8)]
        assert p.status().layer == 3


def test_layer_index_from_the_gcode_layer_tops():
    tr = ZLayerTracker(confirm_polls=1, layer_z=[0.3, 0.5, 0.7, 0.9])
    assert tr.update(0.5, True) is None  # joined mid-print, at layer 1
    trig = tr.update(0.7, True)
    assert trig is not None and trig.layer == 1
    assert tr.update(0.9, False) is None  # paused: Z moves (park) but no layer is done
    assert tr.update(0.7, True) is None
    trig = tr.update(0.88, True)  # a live-Z offset of -0.02 mm: still layer 2 finished
    assert trig is not None and trig.layer == 2


def test_camera_snapshot_and_no_snapshot(fake):
    with _printer(fake) as p:
        img = p.camera(retries=0).grab()
        assert img.shape == (48, 64, 3) and img.dtype == np.uint8
        fake.snapshot = None
        with pytest.raises(CameraError, match="no snapshot yet"):
            p.camera(retries=0).grab()


@pytest.mark.parametrize("url, match", [
    ("prusalink://", "not prusalink://HOST"),
    ("prusalink://printer:99999", "port"),
    ("prusalink://printer?user=a%20b", "user"),
])
def test_bad_urls_are_config_errors(url, match):
    with pytest.raises(ConfigError, match=match):
        prusalink_target(url)


def test_password_never_needed_on_the_command_line(fake, monkeypatch, tmp_path):
    monkeypatch.delenv("LAYERWATCH_PRUSALINK_KEY", raising=False)
    with pytest.raises(PrinterError, match="LAYERWATCH_PRUSALINK_KEY"):
        open_printer(fake.url)
    monkeypatch.setenv("LAYERWATCH_PRUSALINK_KEY", fake.password)
    with open_printer(fake.url) as p:
        assert p.status().state == "printing"
    keyfile = tmp_path / "pl.key"
    keyfile.write_text(fake.password + "\n")
    keyfile.chmod(0o600)
    monkeypatch.delenv("LAYERWATCH_PRUSALINK_KEY")
    with open_printer(fake.url, key_file=keyfile) as p:
        assert p.status().state == "printing"


@pytest.mark.parametrize("kind", sorted(FAULTS))
def test_each_bad_reply_is_one_printer_error(fake, kind):
    with _printer(fake, timeout_s=0.3) as p:
        fake.set_fault(kind)
        with pytest.raises(PrinterError) as err:
            p.status()
        assert "\n" not in str(err.value) and len(str(err.value)) < 400
        fake.set_fault(None)
        assert p.status().state == "printing"


class _Pipe:
    def __init__(self):
        self.seen: list[int] = []

    def process(self, photo, layer_index):
        self.seen.append(layer_index)
        return LayerResult(layer=layer_index, z=0.2, anomaly_ratio=0.0, printed_area_mm2=1000)


def _until(cond, timeout, what):
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.01)


@pytest.mark.slow
def test_monitor_survives_every_prusalink_fault(fake):
    """Every fault kind while printing: the monitor stays up, records each episode, and analyses the next layer."""
    p = _printer(fake, timeout_s=0.3, confirm_polls=1)
    pipe, hist = _Pipe(), History(":memory:")
    job = hist.start_job("prusalink", "part.gcode")
    mon = Monitor(p, SimCamera(lambda n: np.full((48, 64, 3), n % 256, np.uint8)), pipe, PausePolicy(),
                  history=hist, job_id=job, wait_for_verdict=True, faults=FaultSettings(printer_grace_s=0.3))
    out: dict = {}
    t = threading.Thread(target=lambda: out.setdefault("rep", mon.run(poll_s=0.1)), daemon=True)
    t.start()
    try:
        z = 0.2
        for kind in sorted(FAULTS):
            before = mon.report.printer_faults
            fake.set_fault(kind)
            _until(lambda b=before: mon.report.printer_faults >= b + 2, 10, f"failed polls with {kind}")
            fake.set_fault(None)
            _until(lambda: mon.health()["printer"] is None, 5, f"recovery after {kind}")
            assert t.is_alive(), kind
            z, seen = round(z + 0.2, 2), len(pipe.seen)
            fake.z = z
            _until(lambda n=seen: len(pipe.seen) > n, 5, f"a layer analysed after {kind}")
        fake.state = "FINISHED"
        t.join(10)
        rep = out["rep"]
        assert rep.outcome == "done" and rep.pauses == 0 and pipe.seen == list(range(len(FAULTS)))
        kinds = [e["kind"] for e in hist.events(job)]
        assert kinds.count("printer_fault") == len(FAULTS) == kinds.count("printer_recovered")
    finally:
        mon.stop_event.set()
        t.join(5)
        p.close()
        hist.close()


def test_camera_printer_needs_a_camera_and_a_model(fake, tmp_path):
    spec = CameraSpec("printer", None, 0.0, None, 1, 1)
    with _printer(fake) as p:
        with pytest.raises(ConfigError, match="--camera-model"):
            printer_camera(p, spec)
    with VirtualPrinter(b"G1 Z0.2\n") as v, pytest.raises(ConfigError, match="has no camera"):
        printer_camera(v, spec)


@pytest.mark.slow
@pytest.mark.exclusive  # the fake printer moves up a layer each second (tests/xdist_groups.py)
def test_cli_monitor_follows_prusalink_layers_by_the_gcode(fake, monkeypatch, tmp_path):
    """``layerwatch monitor --printer prusalink://... --gcode``: the layers the printer's Z passes, named from the file."""
    tops = [layer.z for layer in read_toolpath(PART_GCODE.read_bytes()).layers]
    monkeypatch.setenv("LAYERWATCH_PRUSALINK_KEY", fake.password)
    fake.z = tops[2]  # the monitor starts during layer 2

    def printer_prints():
        _until(lambda: ("GET", "/api/v1/status") in fake.requests, 60, "the monitor's first poll")
        for z in tops[3:8]:
            time.sleep(1.0)
            fake.z = z + 0.01  # a live-Z offset
        time.sleep(1.5)
        fake.state, fake.progress = "FINISHED", 100.0

    t = threading.Thread(target=printer_prints, daemon=True)
    t.start()
    db = tmp_path / "h.db"
    r = CliRunner().invoke(app, ["monitor", "--printer", fake.url, "--gcode", str(PART_GCODE), "--camera", "sim",
                                 "--config", str(PART_CONFIG), "--history", str(db)])
    t.join(10)
    assert r.exit_code == 0, r.output
    assert "5 layers analysed, 0 pause(s)" in r.output and "outcome done" in r.output
    with History(db) as hist:
        rows = hist.layer_summary(hist.jobs()[0]["id"])
    assert [(row["layer"], row["status"]) for row in rows] == [(n, "ok") for n in range(2, 7)]
    assert not any(p.startswith("/api/v1/job/") for _, p in fake.requests)  # never paused or cancelled
