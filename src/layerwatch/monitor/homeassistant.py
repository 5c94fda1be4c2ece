"""Home Assistant through MQTT discovery: a monitored printer's state, layer, a% and last overlay, and a pause switch.

On connect the bridge publishes (retained) one discovery config per entity under
``<prefix>/<component>/<node>/<object>/config`` (Home Assistant's MQTT discovery; prefix
``homeassistant``):

======================  =========  ==========================================================
object                  component  what
======================  =========  ==========================================================
``state``               sensor     printer state (``printing``, ``paused``, ``unreachable``...)
``layer``               sensor     last analysed layer (0-based)
``anomaly``             sensor     a% of the last analysed layer (paper eq. 5), %
``overlay``             image      the last analysed layer's overlay (PNG/JPEG bytes)
``pause``               switch     on = paused; turning it on pauses, off resumes
======================  =========  ==========================================================

States go to ``layerwatch/<node>/state`` as one retained JSON object (``state``, ``file``,
``progress``, ``layer``, ``anomaly_percent``, ``decision`` of the last layer, ``last_alarm``:
action, layer and reason of the latest warning or pause, usable as an attribute), the overlay to
``layerwatch/<node>/overlay``, availability (``online``/``offline``, the latter also as the
connection's last will) to ``layerwatch/<node>/availability``. A switch command
(``layerwatch/<node>/pause/set``, payload ``ON``/``OFF``) pauses or resumes the printer through
its connector, and is written to the history's audit log and the job's events like the
dashboard's buttons (actor ``home assistant``). Any other payload is ignored with a warning.
"""

from __future__ import annotations

import json
import logging
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from layerwatch.errors import ConfigError, LayerwatchError
from layerwatch.monitor.mqtt import check_topic_part, mqtt_client, tls_context
from layerwatch.monitor.printers.base import Printer
from layerwatch.monitor.printers.keys import resolve_key
from layerwatch.monitor.printers.replies import RateLimitedLog

__all__ = ["HomeAssistantBridge", "BrokerTarget", "broker_target", "discovery_configs", "open_bridge", "MonitorResults",
           "HistoryResults"]

log = logging.getLogger("layerwatch.monitor.homeassistant")

#: largest overlay image published, bytes (Home Assistant keeps retained images in memory)
MAX_IMAGE_BYTES = 8 << 20


class BrokerTarget:
    """An MQTT broker from ``mqtt://host[:port]?user=NAME&node=ID`` (``mqtts://`` with ``&ca=FILE``)."""

    def __init__(self, host: str, port: int, tls: bool, user: str | None, node: str, prefix: str,
                 ca_file: str | None) -> None:
        self.host, self.port, self.tls, self.user = host, port, tls, user
        self.node, self.prefix, self.ca_file = node, prefix, ca_file

    @property
    def where(self) -> str:
        return f"mqtt{'s' if self.tls else ''}://{self.host}:{self.port}"


def broker_target(url: str, default_node: str = "printer") -> BrokerTarget:
    """Parse and check a Home Assistant broker URL.

    Query parameters: ``user`` (the broker's user), ``node`` (this printer's id in the topics,
    default ``default_node``), ``prefix`` (discovery prefix, default ``homeassistant``), ``ca``
    (PEM of the broker's CA, ``mqtts://`` only). The password comes from a key file, the
    environment (``LAYERWATCH_MQTT_KEY``) or the job file, never from the URL.

    Raises
    ------
    ConfigError
        Another scheme, no host, a bad port, node or prefix, a missing CA file.
    """
    parts = urlsplit(url)
    if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
        raise ConfigError("--homeassistant must be mqtt://BROKER[:PORT]?node=ID (or mqtts://...&ca=FILE); "
                          "the broker Home Assistant's MQTT integration uses.")
    try:
        port = parts.port or (8883 if parts.scheme == "mqtts" else 1883)
    except ValueError:
        raise ConfigError("--homeassistant URL has a port that is not a number in 1-65535; fix the URL.") from None
    q = dict(parse_qsl(parts.query))
    node = check_topic_part(q.get("node", default_node), "--homeassistant node")
    prefix = check_topic_part(q.get("prefix", "homeassistant"), "--homeassistant prefix")
    ca = q.get("ca")
    if ca is not None and (parts.scheme != "mqtts" or not Path(ca).expanduser().is_file()):
        raise ConfigError(f"--homeassistant ca={ca}: give an existing PEM file, with mqtts:// only.")
    user = q.get("user") or None
    return BrokerTarget(parts.hostname, port, parts.scheme == "mqtts", user, node, prefix, ca)


def discovery_configs(node: str, prefix: str = "homeassistant", model: str = "printer") -> dict[str, dict[str, Any]]:
    """Topic -> discovery config of each entity (see the module docstring)."""
    base = f"layerwatch/{node}"
    device = {"identifiers": [f"layerwatch_{node}"], "name": f"layerwatch {node}", "manufacturer": "layerwatch",
              "model": model}
    common = {"availability_topic": f"{base}/availability", "device": device}

    def entity(component: str, obj: str, name: str, **kw: Any) -> tuple[str, dict[str, Any]]:
        cfg = {"name": name, "unique_id": f"layerwatch_{node}_{obj}", "object_id": f"layerwatch_{node}_{obj}",
               **common, **kw}
        return f"{prefix}/{component}/{node}/{obj}/config", cfg

    state = {"state_topic": f"{base}/state"}
    return dict([
        entity("sensor", "state", "State", value_template="{{ value_json.state }}", icon="mdi:printer-3d", **state),
        entity("sensor", "layer", "Layer", value_template="{{ value_json.layer }}", state_class="measurement",
               icon="mdi:layers", **state),
        entity("sensor", "anomaly", "Anomaly a%", value_template="{{ value_json.anomaly_percent }}",
               unit_of_measurement="%", state_class="measurement", icon="mdi:alert-decagram", **state),
        entity("image", "overlay", "Last overlay", image_topic=f"{base}/overlay", content_type="image/png"),
        entity("switch", "pause", "Pause", command_topic=f"{base}/pause/set", payload_on="ON", payload_off="OFF",
               state_on="ON", state_off="OFF", icon="mdi:pause-circle",
               value_template="{{ 'ON' if value_json.state in ('paused', 'pausing') else 'OFF' }}", **state),
    ])


class MonitorResults:
    """What an in-process :class:`~layerwatch.monitor.service.Monitor` analysed (one watched job)."""

    def __init__(self, monitor: Any) -> None:
        self.monitor = monitor

    def job_id(self) -> int | None:
        return getattr(self.monitor, "job_id", None)

    def latest(self) -> Any:
        """The last analysed layer's :class:`~layerwatch.analysis.result.LayerResult`, or ``None``."""
        results = self.monitor.report.results
        return results[-1] if results else None

    def image_root(self) -> Path:
        """Folder the results' image paths are relative to."""
        return Path(getattr(self.monitor.pipeline, "image_root", ""))

    def last_alarm(self) -> dict[str, Any] | None:
        """Action, layer and reason of the latest layer whose decision was not "none"."""
        for res in reversed(self.monitor.report.results[-1000:]):
            if res.decision and res.decision != "none":
                return {"action": res.decision, "layer": res.layer, "reason": res.decision_reason[:200]}
        return None


class HistoryResults:
    """What the monitors of ``--follow`` wrote to the history: the newest job of the printer, read like the dashboard.

    Parameters
    ----------
    history : History
        An open connection of its own (SQLite serves the monitor's writes and these reads side by side).
    image_root : Path
        Folder of the stored images (``--images``, default the history's folder).
    printer_prefix : str
        The history's printer label starts with it (``"octoprint:"``); jobs of other printers are ignored.
    """

    def __init__(self, history: Any, image_root: Path, printer_prefix: str) -> None:
        self.history, self.root, self.prefix = history, Path(image_root), printer_prefix

    def job_id(self) -> int | None:
        jid = self.history.last_job_id()
        job = self.history.job(jid) if jid is not None else None
        return jid if job is not None and str(job["printer"]).startswith(self.prefix) else None

    def latest(self) -> Any:
        jid = self.job_id()
        return None if jid is None else self.history.latest_layer(jid)

    def image_root(self) -> Path:
        return self.root

    def last_alarm(self) -> dict[str, Any] | None:
        """The job's latest decision event (an event with a ``layer``, not a camera or printer fault)."""
        jid = self.job_id()
        for e in reversed(self.history.events(jid) if jid is not None else []):
            data = e["data"]
            if isinstance(data, dict) and isinstance(data.get("layer"), int) and \
                    not e["kind"].startswith(("camera", "printer")):
                return {"action": e["kind"], "layer": data["layer"], "reason": str(e["message"])[:200]}
        return None


class HomeAssistantBridge:
    """Publish one printer (and its monitor's results) to Home Assistant; its pause switch drives the printer.

    Parameters
    ----------
    url : str
        Broker URL (:func:`broker_target`).
    printer : Printer
        The connector the switch pauses and resumes.
    password : str, optional
        The broker user's password.
    monitor : Monitor, optional
        Its ``report.results`` give the layer, a% and overlay (:class:`MonitorResults`).
    results : MonitorResults or HistoryResults, optional
        Where the analysed layers come from, instead of ``monitor`` (``--follow``: :class:`HistoryResults`).
    history : History, optional
        Audit log and job events of switch commands.
    job_id : int, optional
        The job the switch commands are logged on (default: the results' current job).
    interval_s : float
        Seconds between two state publications.
    """

    def __init__(self, url: str, printer: Printer, *, password: str | None = None, monitor: Any = None,
                 results: Any = None, history: Any = None, job_id: int | None = None,
                 interval_s: float = 5.0) -> None:
        self.target = broker_target(url, default_node=printer.name)
        if not (math.isfinite(interval_s) and 0.05 <= interval_s <= 3600):
            raise ConfigError("Home Assistant publish interval must be 0.05-3600 s.")
        self.printer, self.history, self._job_id = printer, history, job_id
        self.results = results if results is not None else (MonitorResults(monitor) if monitor is not None else None)
        self.interval_s = float(interval_s)
        base = f"layerwatch/{self.target.node}"
        self.state_topic, self.overlay_topic = f"{base}/state", f"{base}/overlay"
        self.command_topic, self.availability_topic = f"{base}/pause/set", f"{base}/availability"
        self._warn = RateLimitedLog(log)
        self._stop = threading.Event()
        self._connected = threading.Event()
        self._overlay_sent: tuple[int, str] | None = None
        self._commands = ThreadPoolExecutor(max_workers=1, thread_name_prefix="layerwatch-ha")
        tls = tls_context(self.target.ca_file, check_hostname=True) if self.target.tls else None
        self._client = mqtt_client(user=self.target.user, password=password, tls=tls, prefix="layerwatch-ha")
        self._client.will_set(self.availability_topic, "offline", qos=1, retain=True)
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = lambda *a: self._connected.clear()
        self._client.message_callback_add(self.command_topic, self._on_command)
        self._client.connect_async(self.target.host, self.target.port, keepalive=30)
        self._client.loop_start()
        self._thread = threading.Thread(target=self._loop, name="layerwatch-ha-publish", daemon=True)
        self._thread.start()

    # -- MQTT ------------------------------------------------------------------------
    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        if reason.is_failure:
            self._warn.warning("connect", "Home Assistant broker %s refused the connection (%s); check the user "
                               "and LAYERWATCH_MQTT_KEY", self.target.where, reason)
            return
        model = type(self.printer).__name__
        for topic, cfg in discovery_configs(self.target.node, self.target.prefix, model).items():
            client.publish(topic, json.dumps(cfg), qos=1, retain=True)
        client.publish(self.availability_topic, "online", qos=1, retain=True)
        client.subscribe(self.command_topic, qos=1)
        self._connected.set()
        self._overlay_sent = None  # retained messages may be gone (a new broker): send the overlay again
        try:
            self._commands.submit(self.publish_state)  # now, not after the first interval
        except RuntimeError:  # closing
            pass

    def _on_command(self, client: Any, userdata: Any, message: Any) -> None:
        payload = bytes(message.payload[:16]).decode("ascii", "replace").strip().upper()
        action = {"ON": "pause", "OFF": "resume"}.get(payload)
        if action is None:
            self._warn.warning("payload", "Home Assistant pause switch: payload %r ignored (ON or OFF)", payload[:16])
            return
        self._commands.submit(self.command, action)

    def job_id(self) -> int | None:
        """The job switch commands are logged on."""
        if self._job_id is not None or self.results is None:
            return self._job_id
        try:
            return self.results.job_id()
        except LayerwatchError:
            return None

    def command(self, action: str) -> bool:
        """Pause or resume the printer from Home Assistant, audited; whether the printer took it."""
        target, job_id = f"printer {self.printer.name}", self.job_id()
        if self.history is not None:
            try:
                self.history.add_audit(action, f"mqtt {self.target.where}", "home assistant", target,
                                       {"job_id": job_id, "topic": self.command_topic})
            except LayerwatchError as exc:
                log.warning("audit write failed: %s", exc)
        try:
            getattr(self.printer, action)()
        except Exception as exc:  # noqa: BLE001 - a refused or failed command is reported, never fatal
            self._warn.warning("command", "Home Assistant %s of %s failed: %s", action, target, exc)
            ok = False
        else:
            ok = True
        if self.history is not None and job_id is not None:
            try:
                self.history.add_event(job_id, action, f"{action} requested from Home Assistant"
                                       + ("" if ok else " (the printer refused it)"), {"printer": self.printer.name})
            except LayerwatchError as exc:
                log.warning("history write failed: %s", exc)
        self.publish_state()
        return ok

    # -- publishing --------------------------------------------------------------------
    def state(self, res: Any = None) -> dict[str, Any]:
        """The state object published to ``layerwatch/<node>/state`` (``res``: the last analysed layer, if any)."""
        try:
            st = self.printer.status()
            out: dict[str, Any] = {"state": st.state, "file": st.file, "progress": st.progress}
        except Exception as exc:  # noqa: BLE001 - an unreachable printer is a state, not a crash
            out = {"state": "unreachable", "file": None, "progress": None, "error": str(exc)[:200]}
        out["layer"] = None if res is None else res.layer
        ratio = None if res is None or res.status != "ok" else res.anomaly_ratio
        out["anomaly_percent"] = None if ratio is None or not math.isfinite(ratio) else round(100.0 * ratio, 2)
        out["decision"] = None if res is None else (res.decision or None)
        out["last_alarm"] = self.results.last_alarm() if self.results is not None else None
        return out

    def publish_state(self) -> None:
        """Publish the state now (and the overlay, when a newer one exists)."""
        if not self._connected.is_set():
            return
        res = self.results.latest() if self.results is not None else None
        self._client.publish(self.state_topic, json.dumps(self.state(res)), qos=0, retain=True)
        rel = res.images.get("overlay") if res is not None else None
        if self.results is not None and res is not None and rel and (res.layer, rel) != self._overlay_sent:
            self._publish_overlay(self.results.image_root() / rel, res.layer, rel)

    def _publish_overlay(self, path: Path, layer: int, rel: str) -> None:
        try:
            data = path.read_bytes()[:MAX_IMAGE_BYTES + 1]
        except OSError as exc:
            self._warn.warning("overlay", "overlay %s not published: %s", path, exc.strerror)
            return
        if len(data) > MAX_IMAGE_BYTES:
            self._warn.warning("overlay", "overlay %s over %d bytes, not published", path, MAX_IMAGE_BYTES)
            return
        self._client.publish(self.overlay_topic, data, qos=0, retain=True)
        self._overlay_sent = (layer, rel)

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s if self._connected.is_set() else 0.1):
            try:
                self.publish_state()
            except LayerwatchError as exc:  # the history is busy or gone: try again next time
                self._warn.warning("publish", "Home Assistant state not published: %s", exc)
            except Exception:  # noqa: BLE001 - the bridge must never take the monitor down
                log.exception("Home Assistant state publication failed")

    def wait_connected(self, timeout: float = 10.0) -> bool:
        """Wait until the broker accepted the connection and the discovery configs are out."""
        return self._connected.wait(timeout)

    def close(self) -> None:
        """Publish the last state, mark the printer offline, disconnect, and stop the threads (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(5)
        self._commands.shutdown(wait=True)
        if self._connected.is_set():
            try:
                self.publish_state()  # the last word: paused, finished...
            except Exception:  # noqa: BLE001 - closing anyway
                log.exception("Home Assistant final state publication failed")
            self._client.publish(self.availability_topic, "offline", qos=1, retain=True).wait_for_publish(2)
        self._client.disconnect()
        self._client.loop_stop()

    def __enter__(self) -> HomeAssistantBridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_bridge(url: str, printer: Printer, **kw: Any) -> HomeAssistantBridge:
    """A :class:`HomeAssistantBridge` whose broker password comes from ``LAYERWATCH_MQTT_KEY`` (or, warned, ``?key=``).

    ``**kw`` go to :class:`HomeAssistantBridge` (``monitor`` or ``results``, ``history``, ``job_id``, ``interval_s``).
    """
    password, source = resolve_key("mqtt", url)
    log.info("Home Assistant broker password from: %s", source)
    return HomeAssistantBridge(url, printer, password=password, **kw)
