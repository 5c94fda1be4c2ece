"""Moonraker (Klipper) connector: HTTP API + websocket JSON-RPC notifications.

Triggers come from the ``LAYERWATCH_SNAPSHOT`` macro's
``RESPOND MSG="layerwatch snapshot layer=<n> z=<z>"``, delivered as
``notify_gcode_response``; ``print_stats``, ``gcode_move``, ``virtual_sdcard``
and ``webhooks`` are subscribed with ``printer.objects.subscribe`` for state,
file, Z, progress and Klippy's own state (a Klippy shutdown leaves
``print_stats`` at "paused"/"printing", so ``webhooks.state`` wins).
Checked against a real Moonraker 0.11 and Klippy in
``tests/monitor/test_moonraker_real.py``.
"""

from __future__ import annotations

import json
import logging
import math
import re
import threading
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

import httpx
from websockets.sync.client import connect

from layerwatch.errors import LayerwatchError, PrinterError
from layerwatch.gcode.klipper_macros import ack_script
from layerwatch.monitor.printers.base import (
    WS_MAX_FRAME_BYTES,
    WS_RETRY_S,
    Printer,
    PrinterStatus,
    SnapshotTrigger,
    http_request,
    parse_line,
)
from layerwatch.monitor.printers.keys import split_url_key
from layerwatch.monitor.printers.replies import RateLimitedLog, field, reply_json

if TYPE_CHECKING:
    from layerwatch.gcode.objects import PrintObject

__all__ = ["MoonrakerPrinter", "SUBSCRIBE", "clean_objects"]

log = logging.getLogger("layerwatch.monitor.moonraker")

#: Klippy's object name of the hold macro (``layerwatch klipper-config``)
HOLD_MACRO_OBJECT = "gcode_macro LAYERWATCH_SNAPSHOT"

#: JSON-RPC request sent after the websocket opens
SUBSCRIBE = {"jsonrpc": "2.0", "method": "printer.objects.subscribe",
             "params": {"objects": {"print_stats": None, "gcode_move": None, "virtual_sdcard": ["progress"],
                                    "webhooks": ["state", "state_message"]}}, "id": 1}

_HINTS = {503: "Klippy is not running or not ready (check klippy.log; FIRMWARE_RESTART)"}

#: Klippy (``webhooks.state``) states that override print_stats
_KLIPPY_STATES = {"shutdown": "error", "error": "error", "startup": "offline"}

#: Moonraker's Klippy connection notifications -> the webhooks state they imply
_KLIPPY_EVENTS = {"notify_klippy_shutdown": "shutdown", "notify_klippy_disconnected": "startup",
                  "notify_klippy_ready": "ready"}

_STATES = {"printing": "printing", "paused": "paused", "complete": "finished", "cancelled": "cancelled",
           "standby": "idle", "error": "error"}


#: type of each field the connector reads, per printer object; a field of another type is dropped
_FIELDS: dict[str, dict[str, tuple[type, ...]]] = {
    "print_stats": {"state": (str,), "filename": (str,)},
    "gcode_move": {"gcode_position": (list,)},
    "virtual_sdcard": {"progress": (int, float)},
    "webhooks": {"state": (str,), "state_message": (str,)},
}


#: object names this connector sends in EXCLUDE_OBJECT (what slicers and Moonraker's processing write)
_KLIPPER_NAME = re.compile(r"[A-Za-z0-9_.\-]{1,120}")


def _finite(value: Any, lo: float = -math.inf, hi: float = math.inf) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            and lo <= value <= hi)


def clean_objects(status: Any) -> tuple[dict[str, dict[str, Any]], list[str]]:
    """The fields of a Moonraker ``status`` object the connector uses, each of the right type.

    Parameters
    ----------
    status : object
        ``result.status`` of an object query, or ``params[0]`` of ``notify_status_update``.

    Returns
    -------
    objects : dict of str to dict
        Only known objects and fields; ``None`` values are kept (Moonraker sends them for unset
        fields), wrong types, non-finite numbers and short positions are dropped.
    problems : list of str
        One entry per dropped field (``"gcode_move.gcode_position: ..."``).
    """
    out: dict[str, dict[str, Any]] = {}
    problems: list[str] = []
    if not isinstance(status, dict):
        return out, [f"status is {type(status).__name__}, not an object"]
    for obj, fields in status.items():
        known = _FIELDS.get(obj)
        if known is None:
            continue
        if not isinstance(fields, dict):
            problems.append(f"{obj} is {type(fields).__name__}, not an object")
            continue
        for name, value in fields.items():
            kinds = known.get(name)
            if kinds is None or value is None:
                continue
            ok = isinstance(value, kinds) and not isinstance(value, bool)
            if ok and name == "progress":
                ok = _finite(value, 0.0, 1.0)
            elif ok and name == "gcode_position":
                ok = len(value) >= 3 and all(_finite(v) for v in value[:4])
            if ok:
                out.setdefault(obj, {})[name] = value
            else:
                problems.append(f"{obj}.{name}: {str(value)[:40]!r}")
    return out, problems


class MoonrakerPrinter(Printer):
    """Connector for ``moonraker://host:port`` (API key: ``api_key``, or ``?key=`` in the URL).

    Parameters
    ----------
    url : str
        ``moonraker://host:port`` or ``http://host:port``.
    api_key : str, optional
        Moonraker API key (only needed when the host is not a trusted client).
    timeout_s : float
        HTTP timeout, s.
    push : bool
        Open the websocket (``False``: HTTP only; feed frames to :meth:`handle_frame`).
    """

    name = "moonraker"

    def __init__(self, url: str, api_key: str | None = None, *, timeout_s: float = 5.0, push: bool = True) -> None:
        super().__init__()
        bare, url_key = split_url_key(url)
        parts = urlsplit(bare)
        key = api_key or url_key
        self.base = f"http://{parts.netloc}"
        self._warn = RateLimitedLog(log)
        self._http = httpx.Client(base_url=self.base, timeout=timeout_s, headers={"X-Api-Key": key} if key else {})
        self._objects: dict[str, dict[str, Any]] = {}
        self._hold_macro: bool | None = None  # has printer.cfg the LAYERWATCH_SNAPSHOT hold? (asked once)
        self._last_layer: int | None = None
        self._stop = threading.Event()
        self._ws_ready = threading.Event()
        self._thread: threading.Thread | None = None
        if push:
            self._thread = threading.Thread(target=self._ws_loop, name="moonraker-ws", daemon=True)
            self._thread.start()

    # -- HTTP ------------------------------------------------------------------
    def _req(self, method: str, path: str, **kw) -> Any:
        """Send a request; the reply's ``result`` object for a GET, else None (a command's reply is not used)."""
        r = http_request(self._http, method, path, printer="Moonraker", credential="the request",
                         auth_hint="set LAYERWATCH_MOONRAKER_KEY or pass --key-file, or add this host to "
                                   "[authorization] trusted_clients", status_hints=_HINTS, **kw)
        if method != "GET":
            return None
        where = f"Moonraker {method} {path}"
        return field(reply_json(r, where), "result", dict, where, optional=False)

    def server_info(self) -> dict[str, Any]:
        """``/server/info`` result (``klippy_state``, ``moonraker_version``...)."""
        return self._req("GET", "/server/info")

    def status(self) -> PrinterStatus:
        res = self._req("GET", "/printer/objects/query",
                        params={"print_stats": "", "gcode_move": "", "virtual_sdcard": "progress",
                                "webhooks": "state,state_message"})
        objects, problems = clean_objects(field(res, "status", dict, "Moonraker object query", optional=False))
        if problems:
            raise PrinterError(f"Moonraker object query: unexpected value(s) {'; '.join(problems[:3])}; "
                               "unexpected host reply.")
        self._merge(objects)
        return self._status()

    def _status(self) -> PrinterStatus:
        ps = self._objects.get("print_stats", {})
        klippy = str(self._objects.get("webhooks", {}).get("state", "ready"))
        pos = self._objects.get("gcode_move", {}).get("gcode_position")
        prog = self._objects.get("virtual_sdcard", {}).get("progress")
        # After a Klippy shutdown (M112, MCU error) print_stats still says "paused" or "printing":
        # Klippy's own state wins, so a shutdown is never taken for a pause.
        state = _KLIPPY_STATES.get(klippy) or _STATES.get(str(ps.get("state", "standby")), "unknown")
        return PrinterStatus(state, ps.get("filename") or None,
                             self._last_layer, float(pos[2]) if pos and len(pos) > 2 else None,
                             None if prog is None else float(prog))

    def pause(self) -> None:
        self._req("POST", "/printer/print/pause")

    def resume(self) -> None:
        self._req("POST", "/printer/print/resume")

    def cancel(self) -> None:
        self._req("POST", "/printer/print/cancel")

    def send_gcode(self, lines: str | Iterable[str]) -> None:
        script = lines if isinstance(lines, str) else "\n".join(lines)
        self._req("POST", "/printer/gcode/script", params={"script": script})

    def cancel_object(self, obj: PrintObject) -> None:
        """``EXCLUDE_OBJECT NAME=<name>``: the file's own Klipper name, else the object Klipper defines at its centre.

        Raises
        ------
        PrinterError
            Klipper defines no object there (no ``[exclude_object]``, or the file was not labelled
            for it nor processed by Moonraker's object processing).
        """
        name = obj.klipper_name or self._klipper_object_at(obj.center_mm)
        if not _KLIPPER_NAME.fullmatch(name):
            raise PrinterError(f"object name {name!r} is not safe to send to Klipper; rename the object in the slicer.")
        self.send_gcode(f"EXCLUDE_OBJECT NAME={name}")

    def _klipper_object_at(self, center_mm: tuple[float, float], tol_mm: float = 3.0) -> str:
        """Name of the object Klipper's ``exclude_object`` defines nearest ``center_mm`` (within ``tol_mm``)."""
        status = field(self._req("GET", "/printer/objects/query", params={"exclude_object": ""}),
                       "status", dict, "Moonraker objects query")
        objects = (status.get("exclude_object") or {}).get("objects") or []
        best, dist = None, tol_mm
        for o in objects:
            c = o.get("center") if isinstance(o, dict) else None
            if isinstance(c, list) and len(c) == 2 and all(_finite(v) for v in c):
                d = math.hypot(c[0] - center_mm[0], c[1] - center_mm[1])
                if d <= dist and isinstance(o.get("name"), str):
                    best, dist = o["name"], d
        if best is None:
            raise PrinterError(f"Klipper defines no object at ({center_mm[0]:.0f}, {center_mm[1]:.0f}) mm; add "
                               "[exclude_object] to printer.cfg and slice with label objects (or enable "
                               "Moonraker's object processing).")
        return best

    def show_message(self, text: str) -> None:
        """``M117`` (the display, ``display_status.message``) and ``RESPOND`` (the console, Moonraker's gcode store)."""
        errors = []
        for line in (f"M117 {text}", f'RESPOND TYPE=echo MSG="{text}"'):
            try:
                self.send_gcode(line)
            except PrinterError as exc:  # no [display_status] or no [respond]: the other one may still work
                errors.append(str(exc))
        if len(errors) == 2:
            raise PrinterError("; ".join(errors))

    def photo_done(self, trigger: SnapshotTrigger) -> None:
        """End the ``klipper`` profile's hold for this layer (``layerwatch klipper-config`` macros):
        ``SET_GCODE_VARIABLE MACRO=LAYERWATCH_SNAPSHOT VARIABLE=taken VALUE=<layer>``; Klippy runs it
        between two of the hold's short ``LAYERWATCH_WAIT`` steps. Without the macros in printer.cfg
        nothing is sent (the macro's presence is asked once); a failure is logged, never raised."""
        try:
            if self._hold_macro is None:  # the hold macro of `layerwatch klipper-config`, with its `taken` variable
                objects = field(self._req("GET", "/printer/objects/list"), "objects", list, "Moonraker objects")
                self._hold_macro = HOLD_MACRO_OBJECT in objects and "taken" in self._macro_variables()
            if self._hold_macro:
                self.send_gcode(ack_script(trigger.layer))
        except LayerwatchError as exc:
            log.warning("could not end the hold of layer %d (the print goes on after its time-out): %s",
                        trigger.layer, exc)

    def _macro_variables(self) -> dict[str, Any]:
        """The variables of the hold macro (``variable_*`` in printer.cfg), as Klippy reports them."""
        status = field(self._req("GET", "/printer/objects/query", params={HOLD_MACRO_OBJECT: ""}),
                       "status", dict, "Moonraker objects/query")
        return field(status, HOLD_MACRO_OBJECT, dict, "Moonraker objects/query")

    # -- JSON-RPC push ---------------------------------------------------------------
    def _merge(self, objects: dict[str, dict[str, Any]]) -> None:
        """Merge fields already checked by :func:`clean_objects`."""
        for obj, fields in objects.items():
            self._objects.setdefault(obj, {}).update(fields)

    def _merge_status(self, status: Any) -> None:
        objects, problems = clean_objects(status)
        if problems:
            self._warn.warning("frame", "Moonraker websocket: ignored unexpected value(s) %s", "; ".join(problems[:3]))
        self._merge(objects)

    def handle_frame(self, raw: str | bytes | dict) -> None:
        """Process one websocket JSON-RPC frame (notification or subscribe reply).

        A frame that is not JSON, not an object, or has parameters of the wrong
        type is ignored with a rate-limited warning; it never raises.
        """
        try:
            msg = json.loads(raw) if isinstance(raw, (str, bytes)) else raw
        except (ValueError, RecursionError):
            msg = None
        if not isinstance(msg, dict):
            self._warn.warning("frame", "Moonraker websocket: ignored a frame that is not a JSON object")
            return
        method, params = msg.get("method"), msg.get("params")
        params = params if isinstance(params, list) else []
        result = msg.get("result")
        if method == "notify_gcode_response":
            for line in params:
                trig = parse_line(line, source=self.name) if isinstance(line, str) else None
                if trig is not None and (trig.signal or trig.layer != self._last_layer):
                    if not trig.signal:
                        self._last_layer = trig.layer
                    self._emit(trig)
        elif method == "notify_status_update" and params:
            self._merge_status(params[0])
        elif method in _KLIPPY_EVENTS:
            self._merge({"webhooks": {"state": _KLIPPY_EVENTS[method]}})
        elif isinstance(result, dict) and "status" in result:
            self._merge_status(result["status"])
            self._ws_ready.set()

    def wait_connected(self, timeout: float = 10.0) -> bool:
        """Wait until the websocket subscription was answered (triggers flow from then on)."""
        return self._ws_ready.wait(timeout)

    def _ws_loop(self) -> None:
        backoff = WS_RETRY_S[0]
        while not self._stop.is_set():
            try:
                with connect("ws" + self.base[4:] + "/websocket", open_timeout=5, close_timeout=1,
                             max_size=WS_MAX_FRAME_BYTES,
                             additional_headers=dict(self._http.headers.items()) if "x-api-key" in self._http.headers else None) as ws:
                    ws.send(json.dumps(SUBSCRIBE))
                    backoff = WS_RETRY_S[0]
                    while not self._stop.is_set():
                        try:
                            self.handle_frame(ws.recv(timeout=0.5))
                        except TimeoutError:
                            continue
            except Exception as exc:  # noqa: BLE001 - reconnect on anything
                if self._stop.is_set():
                    return
                self._warn.warning("ws", "Moonraker websocket: %s; reconnecting in %.1f s", exc, backoff)
                self._stop.wait(backoff)
                backoff = min(backoff * 2, WS_RETRY_S[1])

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(3.0)
        self._http.close()
