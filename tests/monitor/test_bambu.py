"""The Bambu Lab LAN-mode connector against a real mosquitto (TLS, password) and a fake printer on it.

The connector logs in as ``bblp`` with the access code over TLS (the broker's throwaway
certificate verified as the CA, or not verified without ``?ca=``), asks for a ``pushall``,
follows P1-style partial reports, emits a trigger per finished layer, and sends pause / resume
/ stop / gcode_line, each answered by the printer on its sequence id. Malformed reports, a
silent printer, an unanswered command and a broker restart are faults: the monitor lives
through them and analyses the next layer.
"""

from __future__ import annotations

import gc
import subprocess
import threading
import time

import numpy as np
import pytest
from mqtt_stack import Broker, FakeBambu, need_mqtt

from layerwatch.analysis.result import LayerResult
from layerwatch.cli.monitor import open_printer
from layerwatch.errors import ConfigError, PrinterError
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.health import FaultSettings
from layerwatch.monitor.printers.bambu import BambuPrinter, bambu_target, clean_report
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.storage.history import History

pytestmark = pytest.mark.xdist_group("servers")

SERIAL = "01P00A000000000"

#: malformed reports a printer (or something else on the broker) may publish
BAD_REPORTS = [b"", b"not json", b"[1, 2]", b"null", b'{"print": 5}', b'{"print": {"layer_num": "7"}}',
               b'{"print": {"mc_percent": NaN}}', b'{"print": {"mc_percent": 250, "layer_num": -3}}',
               b'{"print": {"gcode_state": 12, "subtask_name": ["x"]}}', b'{"print": {"layer_num": true}}',
               b"[" * 100_000, b'{"print": {"subtask_name": "' + b"x" * 2000 + b'"}}',
               b'{"print": {"command": "pause", "sequence_id": {"a": 1}, "result": "success"}}']


@pytest.fixture(scope="module")
def broker(tmp_path_factory):
    need_mqtt()
    b = Broker(tmp_path_factory.mktemp("mosquitto"))
    yield b
    b.stop()


@pytest.fixture
def fake(broker):
    f = FakeBambu(broker, SERIAL)
    yield f
    f.close()


def _printer(broker, *, ca=True, code=None, **kw):
    url = f"bambu://127.0.0.1:{broker.tls_port}?serial={SERIAL}" + (f"&ca={broker.cert}" if ca else "")
    p = BambuPrinter(url, code or broker.password, **kw)
    return p


def _until(cond, timeout, what):
    end = time.monotonic() + timeout
    while True:
        try:
            if cond():
                return
        except PrinterError:
            pass
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.02)


def test_status_pushall_and_commands(broker, fake):
    with _printer(broker, ack_timeout_s=3) as p:
        assert p.wait_connected(5)
        _until(lambda: p.status().state == "printing", 5, "the pushall report")
        st = p.status()
        assert (st.file, st.progress) == ("plate_1", 0.0)
        assert any("pushing" in r for r in fake.requests)
        p.pause()
        _until(lambda: p.status().state == "paused", 3, "paused")
        with pytest.raises(PrinterError, match="refused pause"):
            p.pause()
        p.resume()
        _until(lambda: p.status().state == "printing", 3, "printing again")
        p.send_gcode(["M117 layerwatch", "M400"])
        assert fake.gcode == ["M117 layerwatch\nM400\n"]
        p.cancel()
        _until(lambda: p.status().state == "cancelled", 3, "cancelled")
        cmds = [r["print"]["command"] for r in fake.requests if "print" in r]
        assert cmds == ["pause", "pause", "resume", "gcode_line", "stop"]
        assert all(isinstance(r["print"]["sequence_id"], str) for r in fake.requests if "print" in r)


def test_failed_without_our_stop_is_an_error(broker, fake):
    with _printer(broker) as p:
        _until(lambda: p.status().state == "printing", 5, "the first report")
        fake.report(gcode_state="FAILED")
        _until(lambda: p.status().state == "error", 3, "the failure")


def test_layer_triggers_from_layer_num(broker, fake):
    with _printer(broker, layer_z=[0.2 * (i + 1) for i in range(20)]) as p:
        _until(lambda: p.status().state == "printing", 5, "the first report")
        got: list = []
        p.subscribe(got.append)
        for _ in range(4):
            fake.next_layer()
        fake.report(layer_num=5)  # repeated: no second trigger
        _until(lambda: len(got) >= 4, 3, "four triggers")
        time.sleep(0.2)
        trig = p.poll_triggers()
        assert trig == got
        assert [(t.layer, round(t.z, 2)) for t in trig] == [(0, 0.2), (1, 0.4), (2, 0.6), (3, 0.8)]
        assert p.status().layer == 3 and p.status().progress == pytest.approx(0.25)


def test_wrong_access_code_is_a_fault_naming_the_fix(broker):
    with _printer(broker, code="wrong-code") as p:
        time.sleep(0.5)
        with pytest.raises(PrinterError, match="refused the connection.*check the access code"):
            p.status()


def test_unverified_tls_still_connects(broker, fake):
    with _printer(broker, ca=False) as p:
        _until(lambda: p.status().state == "printing", 5, "a report over unverified TLS")


def test_silent_printer_and_unanswered_command(broker, fake):
    with _printer(broker, stale_s=0.3, ack_timeout_s=0.3) as p:
        _until(lambda: p.status().state == "printing", 5, "the first report")
        fake.mute = True
        with pytest.raises(PrinterError, match="did not answer pause"):
            p.pause()
        time.sleep(0.7)
        with pytest.raises(PrinterError, match="has sent no status"):
            p.status()
        # the connector asked again before calling it a fault
        _until(lambda: sum("pushing" in r for r in fake.requests) >= 2, 3, "a second pushall")
        fake.mute = False
        _until(lambda: p.status().state == "printing", 3, "the printer back")


def test_bad_reports_are_dropped(broker, fake):
    with _printer(broker) as p:
        _until(lambda: p.status().state == "printing", 5, "the first report")
        for raw in BAD_REPORTS:
            fake.publish(raw)
        fake.next_layer()
        _until(lambda: p.status().layer == 0, 3, "the layer after the bad reports")
        st = p.status()
        assert st.state == "printing" and st.file == "plate_1" and st.progress == pytest.approx(0.1)


def test_clean_report_checks_every_field():
    fields, problems = clean_report({"print": {"layer_num": 3, "mc_percent": 101, "gcode_state": "RUNNING",
                                               "subtask_name": "a\x00b", "total_layer_num": 2.5}})
    assert fields == {"layer_num": 3, "gcode_state": "RUNNING"}
    assert len(problems) == 3


@pytest.mark.parametrize("url, match", [
    ("bambu://", "bambu://HOST"), ("bambu://printer", "serial"), ("bambu://printer?serial=a/b", "serial"),
    ("bambu://printer?serial=x%23", "serial"), ("bambu://printer:0x1?serial=A1", "port"),
    ("bambu://printer?serial=A1&ca=/nonexistent.pem", "not a file"),
])
def test_bad_urls_are_config_errors(url, match):
    with pytest.raises(ConfigError, match=match):
        bambu_target(url)


def test_access_code_from_the_environment_not_the_command_line(broker, fake, monkeypatch):
    url = f"bambu://127.0.0.1:{broker.tls_port}?serial={SERIAL}&ca={broker.cert}"
    monkeypatch.delenv("LAYERWATCH_BAMBU_KEY", raising=False)
    with pytest.raises(PrinterError, match="LAYERWATCH_BAMBU_KEY"):
        open_printer(url)
    monkeypatch.setenv("LAYERWATCH_BAMBU_KEY", broker.password)
    with open_printer(url) as p:
        _until(lambda: p.status().state == "printing", 5, "a report")


class _Pipe:
    def __init__(self):
        self.seen: list[int] = []

    def process(self, photo, layer_index):
        self.seen.append(layer_index)
        return LayerResult(layer=layer_index, z=0.2, anomaly_ratio=0.0, printed_area_mm2=1000)


@pytest.mark.slow
def test_monitor_survives_bambu_faults(broker, fake):
    """Bad reports, a silent printer and a broker restart: faults recorded, never fatal, the next layer analysed."""
    p = _printer(broker, stale_s=0.4)
    pipe, hist = _Pipe(), History(":memory:")
    job = hist.start_job("bambu", "plate_1")
    mon = Monitor(p, SimCamera(lambda n: np.full((48, 64, 3), n % 256, np.uint8)), pipe, PausePolicy(),
                  history=hist, job_id=job, wait_for_verdict=True, faults=FaultSettings(printer_grace_s=0.3))
    out: dict = {}
    t = threading.Thread(target=lambda: out.setdefault("rep", mon.run(poll_s=0.1)), daemon=True)
    try:
        _until(lambda: p.status().state == "printing", 5, "the first report")
        t.start()
        fake.next_layer()
        _until(lambda: pipe.seen == [0], 5, "layer 0")
        for raw in BAD_REPORTS:
            fake.publish(raw)
        fake.next_layer()
        _until(lambda: pipe.seen == [0, 1], 5, "layer 1 after bad reports")
        fake.mute = True  # silent: no answer to pushall, no reports
        _until(lambda: mon.report.printer_faults >= 2, 5, "a silent printer seen as a fault")
        fake.mute = False
        fake.next_layer()
        _until(lambda: mon.health()["printer"] is None and pipe.seen == [0, 1, 2], 5, "recovery from silence")
        broker.stop()  # the printer's broker restarts (a reboot)
        _until(lambda: mon.report.printer_faults >= 4 and mon.health()["printer"] is not None, 10, "broker down")
        broker.start()  # both clients reconnect by themselves
        _until(lambda: mon.health()["printer"] is None, 15, "reconnected after the broker restart")
        fake.next_layer()
        _until(lambda: pipe.seen == [0, 1, 2, 3], 5, "layer 3 after the restart")
        assert t.is_alive()
        fake.report(gcode_state="FINISH", mc_percent=100)
        t.join(10)
        rep = out["rep"]
        assert rep.outcome == "done" and rep.pauses == 0
        kinds = [e["kind"] for e in hist.events(job)]
        assert kinds.count("printer_fault") == 2 == kinds.count("printer_recovered")
    finally:
        mon.stop_event.set()
        t.join(5)
        p.close()
        hist.close()


# paho-mqtt 2.2 drops the socket of a failed TLS handshake without closing it (collected below)
@pytest.mark.filterwarnings("ignore::ResourceWarning", "ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_certificate_from_another_ca_is_refused(broker, fake, tmp_path):
    other = tmp_path / "other.crt"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=other",
                    "-keyout", str(tmp_path / "other.key"), "-out", str(other)], check=True, capture_output=True)
    url = f"bambu://127.0.0.1:{broker.tls_port}?serial={SERIAL}&ca={other}"
    with BambuPrinter(url, broker.password) as p:
        assert not p.wait_connected(1.0)
        with pytest.raises(PrinterError, match="unreachable: no MQTT connection.*certificate"):
            p.status()
    gc.collect()
