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
import threading
from collections.abc import Iterable
from typing import Any
from urllib.parse import parse_qs, urlsplit

from layerwatch.monitor.printers.base import (
    WS_RETRY_S,
    Printer,
    PrinterStatus,
    http_request,
    parse_trigger,
)

__all__ = ["MoonrakerPrinter", "SUBSCRIBE"]

log = logging.getLogger("layerwatch.monitor.moonraker")

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


class MoonrakerPrinter(Printer):
    """Connector for ``moonraker://host:port[?key=API_KEY]``.

    Parameters
    ----------
    url : str
        ``moonraker://host:port`` or ``http://host:port``.
    timeout_s : float
        HTTP timeout, s.
    push : bool
        Open the websocket (``False``: HTTP only; feed frames to :meth:`handle_frame`).
    """

    name = "moonraker"

    def __init__(self, url: str, *, timeout_s: float = 5.0, push: bool = True) -> None:
        import httpx

        super().__init__()
        parts = urlsplit(url)
        key = (parse_qs(parts.query).get("key") or [None])[0]
        self.base = f"http://{parts.netloc}"
        self._http = httpx.Client(base_url=self.base, timeout=timeout_s, headers={"X-Api-Key": key} if key else {})
        self._objects: dict[str, dict[str, Any]] = {}
        self._last_layer: int | None = None
        self._stop = threading.Event()
        self._ws_ready = threading.Event()
        self._thread: threading.Thread | None = None
        if push:
            self._thread = threading.Thread(target=self._ws_loop, name="moonraker-ws", daemon=True)
            self._thread.start()

    # -- HTTP ------------------------------------------------------------------
    def _req(self, method: str, path: str, **kw) -> Any:
        r = http_request(self._http, method, path, printer="Moonraker", credential="the request",
                         auth_hint="add ?key=API_KEY to the printer URL or add this host to "
                                   "[authorization] trusted_clients", status_hints=_HINTS, **kw)
        return r.json().get("result") if r.content else None

    def server_info(self) -> dict[str, Any]:
        """``/server/info`` result (``klippy_state``, ``moonraker_version``...)."""
        return self._req("GET", "/server/info")

    def status(self) -> PrinterStatus:
        res = self._req("GET", "/printer/objects/query",
                        params={"print_stats": "", "gcode_move": "", "virtual_sdcard": "progress",
                                "webhooks": "state,state_message"})
        self._merge(res.get("status", {}))
        return self._status()

    def _status(self) -> PrinterStatus:
        ps = self._objects.get("print_stats", {})
        klippy = str(self._objects.get("webhooks", {}).get("state", "ready"))
        pos = self._objects.get("gcode_move", {}).get("gcode_position")
        prog = self._objects.get("virtual_sdcard", {}).get("progress")
        # After a Klippy shutdown (M112, MCU error) print_stats still says "paused" or "printing":
        # Klippy's own state wins, so a shutdown is never taken for a pause.
        state = _KLIPPY_STATES.get(klippy) or _STATES.get(str(ps.get("state", "")), "idle")
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

    # -- JSON-RPC push ---------------------------------------------------------------
    def _merge(self, status: dict[str, Any]) -> None:
        for obj, fields in status.items():
            if isinstance(fields, dict):
                self._objects.setdefault(obj, {}).update(fields)

    def handle_frame(self, raw: str | bytes | dict) -> None:
        """Process one websocket JSON-RPC frame (notification or subscribe reply)."""
        try:
            msg = json.loads(raw) if isinstance(raw, (str, bytes)) else raw
        except ValueError:
            return
        if not isinstance(msg, dict):
            return
        method, params = msg.get("method"), msg.get("params") or []
        if method == "notify_gcode_response":
            for line in params:
                trig = parse_trigger(str(line), source=self.name)
                if trig is not None and trig.layer != self._last_layer:
                    self._last_layer = trig.layer
                    self._emit(trig)
        elif method == "notify_status_update" and params and isinstance(params[0], dict):
            self._merge(params[0])
        elif method in _KLIPPY_EVENTS:
            self._merge({"webhooks": {"state": _KLIPPY_EVENTS[method]}})
        elif isinstance(msg.get("result"), dict) and "status" in msg["result"]:
            self._merge(msg["result"]["status"])
            self._ws_ready.set()

    def wait_connected(self, timeout: float = 10.0) -> bool:
        """Wait until the websocket subscription was answered (triggers flow from then on)."""
        return self._ws_ready.wait(timeout)

    def _ws_loop(self) -> None:
        from websockets.sync.client import connect

        backoff = WS_RETRY_S[0]
        while not self._stop.is_set():
            try:
                with connect("ws" + self.base[4:] + "/websocket", open_timeout=5, close_timeout=1,
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
                log.warning("Moonraker websocket: %s; reconnecting in %.1f s", exc, backoff)
                self._stop.wait(backoff)
                backoff = min(backoff * 2, WS_RETRY_S[1])

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(3.0)
        self._http.close()
