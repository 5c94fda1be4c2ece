"""A real mosquitto broker for the MQTT tests, and a fake Bambu Lab printer that speaks its LAN protocol.

:class:`Broker` starts the Debian ``mosquitto`` on two free ports of 127.0.0.1: a TLS listener
with a throwaway self-signed certificate (made with the ``openssl`` CLI) and a password file
(user ``bblp``, as on a Bambu printer), and a plain anonymous listener (Home Assistant's usual
setup). :class:`FakeBambu` is a printer: it subscribes to ``device/{serial}/request``, answers
``pushall``, ``pause``, ``resume``, ``stop`` and ``gcode_line`` as the firmware does (same
command and ``sequence_id``, ``result``), and publishes P1-style partial reports on
``device/{serial}/report``.
"""

from __future__ import annotations

import getpass
import json
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

from polling import free_port

MOSQUITTO = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)


def need_mqtt():
    """Skip (with the reason and the fix) when mosquitto, its tools or paho-mqtt are missing."""
    if MOSQUITTO is None or shutil.which("mosquitto_passwd") is None or shutil.which("openssl") is None:
        pytest.skip("mosquitto (and mosquitto_passwd, openssl) not installed: apt-get install mosquitto openssl")
    pytest.importorskip("paho.mqtt.client", reason="paho-mqtt not installed: pip install 'layerwatch[mqtt]'")


class Broker:
    """One mosquitto process (``tls_port``: TLS + password; ``port``: plain, anonymous)."""

    def __init__(self, folder: Path, password: str = "12345678") -> None:
        self.folder, self.password = folder, password
        self.cert, key = folder / "broker.crt", folder / "broker.key"
        subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj",
                        "/CN=01P00A000000000", "-keyout", str(key), "-out", str(self.cert)],
                       check=True, capture_output=True)
        pw = folder / "passwd"
        pw.write_text("")
        subprocess.run(["mosquitto_passwd", "-b", str(pw), "bblp", password], check=True, capture_output=True)
        pw.chmod(0o600)
        key.chmod(0o600)
        self.port, self.tls_port = free_port(), free_port()
        self.conf = folder / "mosquitto.conf"
        self.conf.write_text(
            # run as us: started as root, mosquitto would switch to a user that cannot read this folder
            f"user {getpass.getuser()}\nper_listener_settings true\npersistence false\nlog_dest stderr\n"
            f"listener {self.tls_port} 127.0.0.1\ncertfile {self.cert}\nkeyfile {key}\n"
            f"allow_anonymous false\npassword_file {pw}\n"
            f"listener {self.port} 127.0.0.1\nallow_anonymous true\n")
        self.proc: subprocess.Popen | None = None
        self.start()

    def start(self) -> None:
        with open(self.folder / "mosquitto.log", "ab") as log:
            self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=subprocess.DEVNULL, stderr=log)
        end = time.monotonic() + 10
        for port in (self.port, self.tls_port):
            while True:
                try:
                    socket.create_connection(("127.0.0.1", port), 0.2).close()
                    break
                except OSError:
                    if self.proc.poll() is not None or time.monotonic() > end:
                        raise RuntimeError("mosquitto did not start: " +
                                           (self.folder / "mosquitto.log").read_text()[-500:]) from None
                    time.sleep(0.05)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(5)
        self.proc = None


def _client(port: int, prefix: str, on_connect=None):
    import paho.mqtt.client as mqtt  # test helper: paho is the optional extra under test

    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"{prefix}-{time.monotonic_ns()}")
    c.on_connect = on_connect
    c.reconnect_delay_set(0.2, 1)
    c.connect("127.0.0.1", port, keepalive=30)
    c.loop_start()
    return c


class FakeBambu:
    """A Bambu printer's MQTT side, printing ``subtask`` from layer 1 of ``total`` layers."""

    def __init__(self, broker: Broker, serial: str = "01P00A000000000", total: int = 20) -> None:
        self.serial, self.total = serial, total
        self.state = {"gcode_state": "RUNNING", "layer_num": 1, "total_layer_num": total, "mc_percent": 0,
                      "subtask_name": "plate_1", "gcode_file": "/data/Metadata/plate_1.gcode"}
        self.requests: list[dict] = []
        self.gcode: list[str] = []
        self.mute = False  # True: requests are not answered (a busy or hung printer)
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self.client = _client(broker.port, "fake-bambu", self._on_connect)
        self.client.on_message = self._on_request
        self._subscribed.wait(5)  # the subscription is in place before the test connects its printer

    def _on_connect(self, client, userdata, flags, reason, properties) -> None:
        client.subscribe(f"device/{self.serial}/request", qos=1)  # again after a broker restart
        self._subscribed.set()

    def publish(self, payload) -> None:
        """Send one report (a dict is JSON-encoded; bytes go out as they are)."""
        data = payload if isinstance(payload, (bytes, str)) else json.dumps(payload)
        self.client.publish(f"device/{self.serial}/report", data, qos=0)  # no wait: also called from paho's thread

    def report(self, **changed) -> None:
        """Change fields and publish only them (as P1/A1 printers do)."""
        with self._lock:
            self.state.update(changed)
        self.publish({"print": {**changed, "command": "push_status", "msg": 1}})

    def next_layer(self) -> None:
        n = self.state["layer_num"] + 1
        self.report(layer_num=n, mc_percent=min(100, round(100 * n / self.total)))

    def _on_request(self, client, userdata, msg) -> None:
        req = json.loads(msg.payload)
        self.requests.append(req)
        if self.mute:
            return
        if "pushing" in req:
            with self._lock:
                full = dict(self.state)
            self.publish({"print": {**full, "command": "push_status", "msg": 0}})
            return
        body = req.get("print", {})
        cmd, seq = body.get("command"), body.get("sequence_id")
        ok, after = {"pause": ("RUNNING", "PAUSE"), "resume": ("PAUSE", "RUNNING"),
                     "stop": (None, "FAILED"), "gcode_line": (None, None)}.get(cmd, ("?", None))
        ok = ok is None or self.state["gcode_state"] == ok
        if ok and cmd == "gcode_line":
            self.gcode.append(body.get("param", ""))
        self.publish({"print": {"command": cmd, "sequence_id": seq, "param": body.get("param", ""),
                                "result": "success" if ok else "fail", "reason": "" if ok else "state"}})
        if ok and after:
            self.report(gcode_state=after)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()
