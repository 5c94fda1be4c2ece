"""Home Assistant MQTT discovery against a real mosquitto: configs, states, overlay, and the pause switch.

A subscriber on the broker (standing in for Home Assistant) sees the retained discovery
configs of the five entities, the state object with the last layer and a%, and the overlay
bytes; a command on the switch topic pauses and resumes the printer (the virtual printer,
and a fake Bambu printer through its own MQTT connector), audited like the dashboard.
"""

from __future__ import annotations

import json
import threading
import time

import cv2
import numpy as np
import pytest
from mqtt_stack import Broker, FakeBambu, need_mqtt
from typer.testing import CliRunner

from layerwatch.analysis.result import LayerResult
from layerwatch.cli import app, main
from layerwatch.errors import ConfigError
from layerwatch.examples import PART_GCODE
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.homeassistant import (
    HistoryResults,
    HomeAssistantBridge,
    broker_target,
    discovery_configs,
)
from layerwatch.monitor.printers.bambu import BambuPrinter
from layerwatch.monitor.printers.base import SnapshotTrigger
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.storage.history import History

pytestmark = pytest.mark.xdist_group("servers")

OVERLAY = cv2.imencode(".png", np.full((32, 48, 3), 200, np.uint8))[1].tobytes()


@pytest.fixture(scope="module")
def broker(tmp_path_factory):
    need_mqtt()
    b = Broker(tmp_path_factory.mktemp("mosquitto-ha"))
    yield b
    b.stop()


class HomeAssistant:
    """What Home Assistant's MQTT integration sees: every message under the discovery prefix and layerwatch/."""

    def __init__(self, broker):
        import paho.mqtt.client as mqtt  # the optional extra under test

        self.messages: dict[str, bytes] = {}
        self.lock = threading.Lock()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"ha-{time.monotonic_ns()}")
        self.client.on_message = self._on_message
        self.client.connect("127.0.0.1", broker.port)
        self.client.subscribe([("homeassistant/#", 1), ("layerwatch/#", 1)])
        self.client.loop_start()

    def _on_message(self, client, userdata, msg):
        with self.lock:
            self.messages[msg.topic] = bytes(msg.payload)

    def get(self, topic):
        with self.lock:
            return self.messages.get(topic)

    def state(self, node):
        raw = self.get(f"layerwatch/{node}/state")
        return None if raw is None else json.loads(raw)

    def press(self, node, payload):
        self.client.publish(f"layerwatch/{node}/pause/set", payload, qos=1).wait_for_publish(5)

    def close(self):
        self.client.disconnect()
        self.client.loop_stop()


@pytest.fixture
def ha(broker):
    h = HomeAssistant(broker)
    yield h
    h.close()


def _until(cond, timeout, what):
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.02)


class OverlayPipeline:
    """Stores an overlay per layer like the artifact store does (path relative to ``image_root``)."""

    def __init__(self, root):
        self.image_root = root

    def process(self, photo, layer_index):
        rel = f"overlays/layer_{layer_index:04d}.png"
        (self.image_root / rel).parent.mkdir(exist_ok=True)
        (self.image_root / rel).write_bytes(OVERLAY)
        return LayerResult(layer=layer_index, z=0.2, anomaly_ratio=0.0123, printed_area_mm2=900,
                           images={"overlay": rel})


def test_discovery_states_overlay_and_pause_switch(broker, ha, tmp_path):
    printer = VirtualPrinter(PART_GCODE.read_bytes(), name="part.gcode")
    hist = History(":memory:")
    job = hist.start_job("virtual", "part.gcode")
    mon = Monitor(printer, SimCamera(lambda n: np.full((48, 64, 3), n, np.uint8)), OverlayPipeline(tmp_path),
                  PausePolicy(), history=hist, job_id=job, wait_for_verdict=True)
    url = f"mqtt://127.0.0.1:{broker.port}?node=mk4_left"
    with HomeAssistantBridge(url, printer, monitor=mon, history=hist, job_id=job, interval_s=0.1) as bridge:
        assert bridge.wait_connected(5)
        want = discovery_configs("mk4_left", model="VirtualPrinter")
        _until(lambda: all(ha.get(t) for t in want), 5, "the discovery configs")
        assert {t: json.loads(ha.get(t)) for t in want} == want
        assert sorted(t.split("/")[1] for t in want) == ["image", "sensor", "sensor", "sensor", "switch"]
        assert ha.get("layerwatch/mk4_left/availability") == b"online"
        _until(lambda: (ha.state("mk4_left") or {}).get("state") == "printing", 3, "the printing state")

        mon.handle_trigger(SnapshotTrigger(layer=4, z=1.0, source="test"))
        _until(lambda: (ha.state("mk4_left") or {}).get("layer") == 4, 3, "layer 4")
        assert ha.state("mk4_left")["anomaly_percent"] == pytest.approx(1.23)
        _until(lambda: ha.get("layerwatch/mk4_left/overlay") == OVERLAY, 3, "the overlay image")

        ha.press("mk4_left", "ON")
        _until(lambda: printer.status().state == "paused", 3, "the switch to pause the printer")
        _until(lambda: ha.state("mk4_left")["state"] == "paused", 3, "the paused state")
        ha.press("mk4_left", "bogus")  # ignored
        ha.press("mk4_left", "OFF")
        _until(lambda: printer.status().state == "printing", 3, "the switch to resume the printer")
        time.sleep(0.3)
        assert printer.pause_count == 1
    # close() waits for the broker to take "offline"; the Home Assistant side receives it from the broker after that
    _until(lambda: ha.get("layerwatch/mk4_left/availability") == b"offline", 3, "offline after close")
    audit = hist.audit()[::-1]  # newest first
    assert [(a["action"], a["actor"], a["target"]) for a in audit] == [
        ("pause", "home assistant", "printer virtual"), ("resume", "home assistant", "printer virtual")]
    assert all(a["client"].startswith("mqtt mqtt://127.0.0.1") for a in audit)
    events = [e["kind"] for e in hist.events(job) if e["kind"] in ("pause", "resume")]
    assert events == ["pause", "resume"]
    hist.close()


def test_switch_pauses_a_bambu_printer_through_its_connector(broker, ha):
    fake = FakeBambu(broker)
    printer = BambuPrinter(f"bambu://127.0.0.1:{broker.tls_port}?serial={fake.serial}&ca={broker.cert}",
                           broker.password)
    try:
        with HomeAssistantBridge(f"mqtt://127.0.0.1:{broker.port}?node=x1", printer, interval_s=0.1) as bridge:
            assert bridge.wait_connected(5)
            _until(lambda: (ha.state("x1") or {}).get("state") == "printing", 5, "the printing state")
            ha.press("x1", "ON")
            _until(lambda: fake.state["gcode_state"] == "PAUSE", 5, "the fake printer paused")
            _until(lambda: ha.state("x1")["state"] == "paused", 3, "the paused state in Home Assistant")
            ha.press("x1", "OFF")
            _until(lambda: fake.state["gcode_state"] == "RUNNING", 5, "the fake printer resumed")
    finally:
        printer.close()
        fake.close()


def test_unreachable_printer_is_a_state(broker, ha):
    fake = FakeBambu(broker)
    printer = BambuPrinter(f"bambu://127.0.0.1:{broker.tls_port}?serial=NOPRINTER", broker.password, stale_s=0.2)
    try:
        with HomeAssistantBridge(f"mqtt://127.0.0.1:{broker.port}?node=p1s", printer, interval_s=0.1):
            _until(lambda: "has sent no status" in (ha.state("p1s") or {}).get("error", ""), 5,
                   "the unreachable state of a printer that never reports")
            assert ha.state("p1s")["state"] == "unreachable"
    finally:
        printer.close()
        fake.close()


@pytest.mark.parametrize("url, match", [
    ("http://broker", "mqtt://BROKER"), ("mqtt://broker?node=a/b", "node"), ("mqtt://broker?node=%23", "node"),
    ("mqtt://broker?prefix=ha+x", "prefix"), ("mqtt://broker?ca=/etc/hostname", "mqtts:// only"),
    ("mqtt://broker:70000", "port"),
])
def test_bad_broker_urls_are_config_errors(url, match):
    with pytest.raises(ConfigError, match=match):
        broker_target(url)


def test_broker_url_defaults():
    t = broker_target("mqtts://ha.local?user=layerwatch", default_node="bambu")
    assert (t.host, t.port, t.tls, t.user, t.node, t.prefix) == ("ha.local", 8883, True, "layerwatch", "bambu",
                                                                 "homeassistant")


@pytest.mark.slow
def test_cli_monitor_publishes_to_home_assistant(broker, ha, tmp_path):
    """``layerwatch monitor --homeassistant``: discovery, the layers as they are analysed, the pause it made."""
    r = CliRunner().invoke(app, ["monitor", "--printer", "virtual", "--camera", "sim", "--failure", "spaghetti",
                                 "--onset", "6", "--history", str(tmp_path / "h.db"),
                                 "--homeassistant", f"mqtt://127.0.0.1:{broker.port}?node=cli_virtual"])
    assert r.exit_code == 0, r.output
    assert "1 pause(s)" in r.output
    _until(lambda: ha.get("homeassistant/switch/cli_virtual/pause/config") is not None, 3, "the switch config")
    _until(lambda: ha.get("layerwatch/cli_virtual/availability") == b"offline", 3, "offline after the run")
    st = ha.state("cli_virtual")
    assert st["state"] == "paused" and st["layer"] >= 6
    alarm = st["last_alarm"]
    assert alarm["action"] == "pause" and alarm["layer"] >= 6 and "PAUSE" in r.output
    overlay = ha.get("layerwatch/cli_virtual/overlay")  # stored beside the history, as the dashboard reads them
    assert overlay is not None and overlay.startswith(b"\x89PNG")
    assert cv2.imdecode(np.frombuffer(overlay, np.uint8), cv2.IMREAD_COLOR).shape[0] > 100


def test_cli_rejects_a_bad_broker_url_before_connecting(capsys):
    assert main(["monitor", "--printer", "virtual", "--homeassistant", "mqtt://h?node=a/b"]) == 2
    assert "--homeassistant node 'a/b' must be" in capsys.readouterr().err


def test_follow_mode_reads_the_newest_job_from_the_history(broker, ha, tmp_path):
    """``--follow``: layers, a%, overlay and alarm as the monitors wrote them to the history (and the image folder)."""
    (tmp_path / "jobs").mkdir()
    (tmp_path / "jobs" / "l3.png").write_bytes(OVERLAY)
    writer = History(tmp_path / "h.db")
    job = writer.start_job("virtual:http://127.0.0.1:1", "a.gcode")
    for n in range(4):
        writer.add_layer(job, LayerResult(layer=n, z=0.2 * (n + 1), anomaly_ratio=0.01 * n, printed_area_mm2=500,
                                          images={"overlay": "jobs/l3.png"} if n == 3 else {}))
    writer.add_event(job, "notify", "a% 2.0 above the warn ratio", {"layer": 2})
    writer.add_event(job, "camera_fault", "frame too dark", {"layer": 3})
    printer = VirtualPrinter(PART_GCODE.read_bytes(), name="a.gcode")
    reader = History(tmp_path / "h.db")
    url = f"mqtt://127.0.0.1:{broker.port}?node=follow"
    with HomeAssistantBridge(url, printer, results=HistoryResults(reader, tmp_path, "virtual:"), history=reader,
                             interval_s=0.1) as bridge:
        assert bridge.wait_connected(5)
        _until(lambda: (ha.state("follow") or {}).get("layer") == 3, 3, "layer 3 from the history")
        st = ha.state("follow")
        assert st["anomaly_percent"] == pytest.approx(3.0)
        assert st["last_alarm"] == {"action": "notify", "layer": 2, "reason": "a% 2.0 above the warn ratio"}
        _until(lambda: ha.get("layerwatch/follow/overlay") == OVERLAY, 3, "the stored overlay")
        ha.press("follow", "ON")
        _until(lambda: printer.status().state == "paused", 3, "the pause")
        _until(lambda: any(e["kind"] == "pause" for e in writer.events(job)), 3, "the pause logged on the job")
        other = writer.start_job("octoprint:http://elsewhere", "b.gcode")  # another printer's newer job
        writer.add_layer(other, LayerResult(layer=9, z=2.0, anomaly_ratio=0.5, printed_area_mm2=500))
        time.sleep(0.4)
        assert ha.state("follow")["layer"] is None  # not this printer's job
    reader.close()
    writer.close()
