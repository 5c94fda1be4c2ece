"""Bambu Lab connector in LAN mode: MQTT over TLS (port 8883, user ``bblp``, password = access code).

Protocol (as the printers speak it and the open-source LAN-mode clients document it):

- reports on ``device/{serial}/report``: ``{"print": {...}}`` with ``gcode_state`` (``IDLE``,
  ``PREPARE``, ``RUNNING``, ``PAUSE``, ``FINISH``, ``FAILED``), ``layer_num`` (1-based, the
  layer being printed), ``total_layer_num``, ``mc_percent`` (%), ``subtask_name`` and
  ``gcode_file``. P1/A1 printers send only the fields that changed, so reports are merged;
  a full report is asked for with ``{"pushing": {"command": "pushall"}}``;
- requests on ``device/{serial}/request``: ``{"print": {"command": "pause" | "resume" |
  "stop" | "gcode_line", "sequence_id": "<n>", "param": ...}}``, answered on the report topic
  by a message with the same command and ``sequence_id`` and ``result`` ``"success"``/``"fail"``.

Every report is validated field by field (type, range); a bad message is dropped with a
rate-limited warning, never trusted. :meth:`BambuPrinter.status` raises
:class:`~layerwatch.errors.PrinterError` while the broker is unreachable or the printer has
sent nothing for ``stale_s`` (a pushall is asked for first), so the monitor counts a fault
and retries, as it does for OctoPrint and Moonraker.

Layer changes come from ``layer_num``: when it moves from ``n`` to ``n + 1``, layer ``n - 1``
(0-based) is done and its snapshot trigger is emitted (the photo is taken while the next layer
prints: Bambu firmware has no park hold). The camera of P1/A1 printers is
:class:`~layerwatch.monitor.printers.bambu_camera.BambuCamera`.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import threading
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from layerwatch.errors import ConfigError, LayerwatchError, PrinterError
from layerwatch.monitor.mqtt import MAX_MESSAGE_BYTES, check_topic_part, mqtt_client, tls_context
from layerwatch.monitor.printers.bambu_camera import BambuCamera
from layerwatch.monitor.printers.base import Printer, PrinterStatus, SnapshotTrigger
from layerwatch.monitor.printers.keys import ENV_VARS
from layerwatch.monitor.printers.replies import RateLimitedLog, parse_json

__all__ = ["BambuPrinter", "BambuTarget", "bambu_target", "clean_report", "GCODE_STATES"]

log = logging.getLogger("layerwatch.monitor.bambu")

#: Bambu ``gcode_state`` -> PrinterStatus.state ("FAILED" also follows a stop: "cancelled" when
#: this connector sent the stop)
GCODE_STATES = {"IDLE": "idle", "PREPARE": "printing", "SLICING": "printing", "RUNNING": "printing",
                "PAUSE": "paused", "FINISH": "finished", "FAILED": "error", "INIT": "offline", "OFFLINE": "offline"}

#: field -> (types, lo, hi) of the ``print`` object fields the connector uses
_FIELDS: dict[str, tuple[tuple[type, ...], float, float]] = {
    "gcode_state": ((str,), 0, 64), "subtask_name": ((str,), 0, 512), "gcode_file": ((str,), 0, 1024),
    "layer_num": ((int,), 0, 1_000_000), "total_layer_num": ((int,), 0, 1_000_000),
    "mc_percent": ((int, float), 0, 100),
}


def clean_report(msg: Any) -> tuple[dict[str, Any], list[str]]:
    """The fields of one report's ``print`` object the connector uses, each of the right type and range.

    Returns
    -------
    fields : dict
        Known fields only; strings are length-checked, numbers finite and in range.
    problems : list of str
        One entry per dropped field.
    """
    body = msg.get("print") if isinstance(msg, dict) else None
    if not isinstance(body, dict):
        return {}, [] if isinstance(msg, dict) else [f"report is {type(msg).__name__}, not an object"]
    out: dict[str, Any] = {}
    problems: list[str] = []
    for name, (kinds, lo, hi) in _FIELDS.items():
        if name not in body:
            continue
        value = body[name]
        ok = isinstance(value, kinds) and not isinstance(value, bool)
        if ok and isinstance(value, str):
            ok = lo <= len(value) <= hi and value.isprintable()
        elif ok:
            ok = math.isfinite(value) and lo <= value <= hi
        if ok:
            out[name] = value
        else:
            problems.append(f"print.{name}: {json.dumps(value, default=str)[:40]}")
    return out, problems


class BambuTarget:
    """Where a ``bambu://host[:port]?serial=SERIAL[&ca=FILE]`` printer is.

    Attributes
    ----------
    host : str
    port : int
        MQTT port (8883).
    serial : str
        The printer's serial number (topic part).
    ca_file : str or None
        CA certificate to verify the printer's TLS certificate with.
    """

    def __init__(self, host: str, port: int, serial: str, ca_file: str | None) -> None:
        self.host, self.port, self.serial, self.ca_file = host, port, serial, ca_file


def bambu_target(url: str) -> BambuTarget:
    """Parse and check a ``bambu://`` printer URL.

    Raises
    ------
    ConfigError
        No host, a bad port, a missing or malformed serial, a CA file that does not exist.
    """
    parts = urlsplit(url)
    if parts.scheme != "bambu" or not parts.hostname:
        raise ConfigError("printer URL must be bambu://HOST?serial=SERIAL (the printer's address and the serial "
                          "number from its Settings > Device).")
    try:
        port = parts.port or 8883
    except ValueError:
        raise ConfigError("bambu:// URL has a port that is not a number in 1-65535; fix the URL.") from None
    query = dict(parse_qsl(parts.query))
    if "serial" not in query:
        raise ConfigError("bambu:// URL needs ?serial=SERIAL (the printer's serial number, Settings > Device).")
    serial = check_topic_part(query["serial"], "bambu:// serial")
    ca = query.get("ca")
    if ca is not None and not Path(ca).expanduser().is_file():
        raise ConfigError(f"bambu:// ?ca={ca} is not a file; give the PEM of the CA that signed the printer's certificate.")
    return BambuTarget(parts.hostname, port, serial, ca)


class BambuPrinter(Printer):
    """Connector for ``bambu://host[:port]?serial=SERIAL[&ca=FILE]`` (access code: ``access_code``).

    Parameters
    ----------
    url : str
        See :func:`bambu_target`.
    access_code : str
        The LAN access code shown on the printer (Settings > WLAN / LAN only mode).
    stale_s : float
        A printer silent this long gets a pushall request; silent twice as long is a fault, s (a
        printing P1 reports temperatures every few seconds; pushall is costly for it, so not more
        often than this).
    ack_timeout_s : float
        How long a command waits for the printer's answer, s.
    layer_z : sequence of float, optional
        Top Z of each layer of the job's G-code, mm (for the triggers' ``z``; 0 without it:
        Bambu reports no height).
    """

    name = "bambu"

    def __init__(self, url: str, access_code: str | None, *, stale_s: float = 60.0, ack_timeout_s: float = 5.0,
                 layer_z: Sequence[float] | None = None) -> None:
        super().__init__()
        self.target = bambu_target(url)
        if not access_code:
            raise PrinterError(f"Bambu LAN mode needs the printer's access code (Settings > WLAN); set "
                               f"{ENV_VARS['bambu']}, pass --key-file FILE or put api_key in the job file's [host] section.")
        for what, v in (("stale_s", stale_s), ("ack_timeout_s", ack_timeout_s)):
            if not (math.isfinite(v) and 0 < v <= 3600):
                raise ConfigError(f"Bambu {what} must be 0-3600 s.")
        self.stale_s, self.ack_timeout_s = float(stale_s), float(ack_timeout_s)
        self.layer_z = None if layer_z is None else [float(z) for z in layer_z]
        self.report_topic = f"device/{self.target.serial}/report"
        self.request_topic = f"device/{self.target.serial}/request"
        self._state: dict[str, Any] = {}
        self._last_report: float | None = None
        self._last_layer: int | None = None
        self._stopped = False  # this connector sent "stop": FAILED means cancelled
        self._connected = threading.Event()
        self._disconnect_reason = "not connected yet"
        self._acks: dict[str, dict[str, Any]] = {}
        self._ack_cv = threading.Condition()
        self._seq = itertools.count(int(time.time()) % 1_000_000)
        self._warn = RateLimitedLog(log)
        self._access_code = access_code  # for the camera's login
        self._client = mqtt_client(user="bblp", password=access_code, tls=tls_context(self.target.ca_file),
                                   prefix="layerwatch-bambu")
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = self._on_disconnect
        self._client.on_connect_fail = self._on_connect_fail
        self._client.on_message = self._on_message
        self._client.connect_async(self.target.host, self.target.port, keepalive=30)
        self._client.loop_start()

    # -- MQTT callbacks (paho's network thread) -----------------------------------
    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        if reason.is_failure:
            self._disconnect_reason = f"the printer refused the connection ({reason}); check the access code"
            return
        client.subscribe(self.report_topic, qos=0)
        self._connected.set()
        self.push_all()

    def _on_connect_fail(self, client: Any, userdata: Any) -> None:
        self._disconnect_reason = ("no MQTT connection (host down, port closed, or a TLS certificate that "
                                   "?ca= does not verify)")

    def _on_disconnect(self, client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        if self._connected.is_set():  # a refused login keeps its own reason
            self._disconnect_reason = f"disconnected ({reason})"
        self._connected.clear()
        with self._lock:  # what it said before the break proves nothing now: wait for a fresh report
            self._last_report = None

    def _on_message(self, client: Any, userdata: Any, message: Any) -> None:
        try:
            self.handle_report(message.payload)
        except Exception:  # noqa: BLE001 - a bad message must not kill paho's network thread
            log.exception("Bambu report handling failed; the message was dropped")

    def handle_report(self, payload: bytes | str) -> None:
        """Merge one report message into the printer's state; emit the trigger of a finished layer."""
        if len(payload) > MAX_MESSAGE_BYTES:
            self._warn.warning("size", "Bambu report of %d bytes dropped (limit %d)", len(payload), MAX_MESSAGE_BYTES)
            return
        try:
            msg = parse_json(payload, "Bambu report")
        except PrinterError as exc:
            self._warn.warning("json", "%s", exc)
            return
        self._ack(msg)
        fields, problems = clean_report(msg)
        if problems:
            self._warn.warning("fields", "Bambu report fields dropped: %s", "; ".join(problems))
        if not isinstance(msg, dict) or not isinstance(msg.get("print"), dict):
            return
        with self._lock:
            old_layer, old_file = self._state.get("layer_num"), self._state.get("subtask_name")
            self._state.update(fields)
            self._last_report = time.monotonic()
            new_layer = self._state.get("layer_num")
            if self._state.get("subtask_name") != old_file:  # another job: layers from its start
                self._last_layer = None
        if isinstance(new_layer, int) and isinstance(old_layer, int) and new_layer == old_layer + 1 and old_layer >= 1:
            self._layer_done(old_layer - 1)

    def _layer_done(self, index: int) -> None:
        if index == self._last_layer:
            return
        self._last_layer = index
        z = self.layer_z[index] if self.layer_z and index < len(self.layer_z) else 0.0
        self._emit(SnapshotTrigger(layer=index, z=z, source=self.name))

    def _ack(self, msg: Any) -> None:
        body = msg.get("print") if isinstance(msg, dict) else None
        if not isinstance(body, dict):
            return
        seq = body.get("sequence_id")
        if isinstance(seq, (str, int)) and not isinstance(seq, bool) and "result" in body:
            with self._ack_cv:
                self._acks[str(seq)] = body
                self._ack_cv.notify_all()

    # -- Printer interface -----------------------------------------------------------
    def push_all(self) -> None:
        """Ask the printer for a full report (P1/A1 send only changes otherwise)."""
        payload = {"pushing": {"sequence_id": str(next(self._seq)), "command": "pushall"}}
        self._client.publish(self.request_topic, json.dumps(payload), qos=0)

    def status(self) -> PrinterStatus:
        where = f"Bambu printer {self.target.serial} at {self.target.host}:{self.target.port}"
        if not self._connected.is_set():
            raise PrinterError(f"{where} unreachable: {self._disconnect_reason}; check that LAN mode is on and "
                               "the printer is powered.")
        with self._lock:
            state, last = dict(self._state), self._last_report
        age = math.inf if last is None else time.monotonic() - last
        if age > self.stale_s:
            self.push_all()
        if age > 2 * self.stale_s or "gcode_state" not in state:
            since = "since the connection opened" if last is None else f"for {age:.0f} s"
            raise PrinterError(f"{where} has sent no status {since}; a pushall was requested, "
                               "check the printer's network.")
        raw = str(state["gcode_state"]).upper()
        text = GCODE_STATES.get(raw, "unknown")
        if raw == "FAILED" and self._stopped:
            text = "cancelled"
        pct = state.get("mc_percent")
        return PrinterStatus(text, state.get("subtask_name") or state.get("gcode_file"), self._last_layer, None,
                             None if pct is None else pct / 100.0)

    def _command(self, command: str, param: str = "") -> None:
        """Publish one ``print`` command and wait for the printer's answer to its sequence id."""
        where = f"Bambu printer {self.target.serial}"
        if not self._connected.is_set():
            raise PrinterError(f"{where} unreachable ({self._disconnect_reason}); {command} was not sent.")
        seq = str(next(self._seq))
        body = {"print": {"command": command, "sequence_id": seq, "param": param}}
        info = self._client.publish(self.request_topic, json.dumps(body), qos=1)
        if info.rc != 0:
            raise PrinterError(f"{where}: {command} could not be sent (MQTT error {info.rc}); check the connection.")
        deadline = time.monotonic() + self.ack_timeout_s
        with self._ack_cv:
            while seq not in self._acks:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise PrinterError(f"{where} did not answer {command} within {self.ack_timeout_s:g} s; "
                                       "check the printer's screen.")
                self._ack_cv.wait(left)
            answer = self._acks.pop(seq)
        if answer.get("result") != "success":
            reason = str(answer.get("reason") or answer.get("result"))[:80]
            raise PrinterError(f"{where} refused {command} ({reason}); is the job in a state for it?")

    def pause(self) -> None:
        self._command("pause")

    def resume(self) -> None:
        self._command("resume")

    def cancel(self) -> None:
        self._stopped = True
        try:
            self._command("stop")
        except LayerwatchError:
            self._stopped = False
            raise

    def send_gcode(self, lines: str | Iterable[str]) -> None:
        text = lines if isinstance(lines, str) else "\n".join(lines)
        self._command("gcode_line", text.rstrip("\n") + "\n")

    def camera(self, **kw: Any) -> BambuCamera:
        """The P1/A1 camera of this printer (TCP 6000, same access code and ``?ca=``); see :mod:`.bambu_camera`."""
        return BambuCamera(self.target.host, self._access_code, ca_file=self.target.ca_file, **kw)

    def wait_connected(self, timeout: float = 10.0) -> bool:
        """Wait until the broker accepted the connection."""
        return self._connected.wait(timeout)

    def close(self) -> None:
        self._client.disconnect()
        self._client.loop_stop()
