"""OctoPrint connector: REST with ``X-Api-Key`` and the SockJS websocket push.

Triggers: ``@layerwatch ...`` host commands reach only OctoPrint plugins
(the ``octoprint.comm.protocol.atcommand`` hooks), so the connector watches
the firmware's echo of the ``M118 E1 layerwatch snapshot layer=<n> z=<z>``
line, which OctoPrint pushes as ``Recv: echo:layerwatch snapshot ...`` in the
``current.logs`` of its websocket (``/sockjs/websocket``, authenticated with
the session from a passive ``/api/login``).
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Iterable
from typing import Any
from urllib.parse import parse_qs, urlsplit

from layerwatch.errors import PrinterError
from layerwatch.monitor.printers.base import (
    WS_RETRY_S,
    Printer,
    PrinterStatus,
    http_request,
    parse_trigger,
)

__all__ = ["OctoPrintPrinter", "parse_octoprint_message"]

log = logging.getLogger("layerwatch.monitor.octoprint")

_HINTS = {409: "the printer is not connected, or the job is not in a state for this command"}

#: OctoPrint job state (``/api/job`` ``state``, matched by prefix) -> PrinterStatus.state.
#: "Pausing", "Resuming" and "Cancelling" stay transient: OctoPrint ignores a resume until
#: the job is really "Paused", and a cancelling job may still move.
_STATES = {"printing": "printing", "paused": "paused", "pausing": "pausing", "resuming": "resuming",
           "cancelling": "cancelling", "operational": "idle", "finishing": "printing",
           "starting": "printing", "offline": "offline", "opening serial": "offline",
           "detecting serial": "offline", "connecting": "offline", "closed": "offline", "error": "error"}


def parse_octoprint_message(msg: dict[str, Any], source: str = "octoprint") -> list:
    """Snapshot triggers in one decoded websocket message (``current``/``history`` logs)."""
    out = []
    for key in ("current", "history"):
        body = msg.get(key)
        if not isinstance(body, dict):
            continue
        for line in body.get("logs") or []:
            if isinstance(line, str) and line.startswith("Recv:"):
                trig = parse_trigger(line[5:], source=source)
                if trig is not None:
                    out.append(trig)
    return out


class OctoPrintPrinter(Printer):
    """Connector for ``octoprint://host:port?key=API_KEY`` (or ``url`` + ``api_key``).

    Parameters
    ----------
    url : str
        ``http://host:port`` (``octoprint://`` is accepted; ``?key=`` gives the key).
    api_key : str, optional
    timeout_s : float
        HTTP timeout, s.
    push : bool
        Open the websocket and deliver triggers (``False``: REST only).
    """

    name = "octoprint"

    def __init__(self, url: str, api_key: str | None = None, *, timeout_s: float = 5.0, push: bool = True) -> None:
        import httpx

        super().__init__()
        parts = urlsplit(url)
        api_key = api_key or (parse_qs(parts.query).get("key") or [None])[0]
        if not api_key:
            raise PrinterError("OctoPrint needs an API key; pass octoprint://host:port?key=... (Settings > API).")
        self.base = f"http://{parts.netloc}{parts.path.rstrip('/')}"
        self._http = httpx.Client(base_url=self.base, headers={"X-Api-Key": api_key}, timeout=timeout_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_layer: int | None = None
        self._ws_ready = threading.Event()
        #: ``listener(message)`` for every decoded websocket message (e.g. the M114 reply of parked.py)
        self.listeners: list = []
        if push:
            self._thread = threading.Thread(target=self._ws_loop, name="octoprint-ws", daemon=True)
            self._thread.start()

    # -- REST --------------------------------------------------------------
    def _req(self, method: str, path: str, **kw) -> Any:
        r = http_request(self._http, method, path, printer="OctoPrint", credential="the API key",
                         auth_hint="copy the key from Settings > API", status_hints=_HINTS, **kw)
        return r.json() if r.content and "json" in r.headers.get("content-type", "") else None

    def status(self) -> PrinterStatus:
        job = self._req("GET", "/api/job")
        st = str(job.get("state", "")).lower()
        state = next((v for k, v in _STATES.items() if st.startswith(k)), "idle")
        f = (job.get("job") or {}).get("file") or {}
        prog = (job.get("progress") or {}).get("completion")
        return PrinterStatus(state, f.get("name"), self._last_layer, None, None if prog is None else prog / 100.0)

    def pause(self) -> None:
        self._req("POST", "/api/job", json={"command": "pause", "action": "pause"})

    def resume(self) -> None:
        """Resume a paused job; refuses while OctoPrint is still "Pausing" (it would ignore the resume)."""
        if self.status().state == "pausing":
            raise PrinterError("OctoPrint is still pausing the job and would ignore a resume; "
                               "resume once it shows Paused.")
        self._req("POST", "/api/job", json={"command": "pause", "action": "resume"})

    def cancel(self) -> None:
        self._req("POST", "/api/job", json={"command": "cancel"})

    def send_gcode(self, lines: str | Iterable[str]) -> None:
        cmds = [lines] if isinstance(lines, str) else list(lines)
        self._req("POST", "/api/printer/command", json={"commands": cmds})

    # -- push ----------------------------------------------------------------
    def _ws_loop(self) -> None:
        from websockets.sync.client import connect

        backoff = WS_RETRY_S[0]
        ws_url = "ws" + self.base[4:] + "/sockjs/websocket"
        while not self._stop.is_set():
            try:
                login = self._req("POST", "/api/login", json={"passive": True})
                with connect(ws_url, open_timeout=5, close_timeout=1) as ws:
                    ws.send(json.dumps({"auth": f"{login['name']}:{login['session']}"}))
                    backoff = WS_RETRY_S[0]
                    while not self._stop.is_set():
                        try:
                            raw = ws.recv(timeout=0.5)
                        except TimeoutError:
                            continue
                        self._ws_ready.set()
                        self._on_message(raw)
            except Exception as exc:  # noqa: BLE001 - reconnect on anything
                if self._stop.is_set():
                    return
                log.warning("OctoPrint websocket: %s; reconnecting in %.1f s", exc, backoff)
                self._stop.wait(backoff)
                backoff = min(backoff * 2, WS_RETRY_S[1])

    def _on_message(self, raw: str | bytes) -> None:
        try:
            msg = json.loads(raw)
        except ValueError:
            return
        for listener in list(self.listeners) if isinstance(msg, dict) else ():
            listener(msg)
        for trig in parse_octoprint_message(msg if isinstance(msg, dict) else {}, self.name):
            if trig.layer != self._last_layer:
                self._last_layer = trig.layer
                self._emit(trig)

    def wait_connected(self, timeout: float = 10.0) -> bool:
        """Wait until the websocket delivered its first message."""
        return self._ws_ready.wait(timeout)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(3.0)
        self._http.close()
