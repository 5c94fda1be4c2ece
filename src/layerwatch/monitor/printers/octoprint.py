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
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

import httpx
from websockets.sync.client import connect

from layerwatch.errors import PrinterError
from layerwatch.monitor.printers.base import (
    WS_MAX_FRAME_BYTES,
    WS_RETRY_S,
    Printer,
    PrinterStatus,
    http_request,
    parse_line,
)
from layerwatch.monitor.printers.keys import ENV_VARS, split_url_key
from layerwatch.monitor.printers.replies import (
    RateLimitedLog,
    field,
    number_field,
    reply_json,
    text_field,
)

if TYPE_CHECKING:
    from layerwatch.gcode.objects import PrintObject

__all__ = ["OctoPrintPrinter", "parse_octoprint_message", "parse_job"]

log = logging.getLogger("layerwatch.monitor.octoprint")

_HINTS = {409: "the printer is not connected, or the job is not in a state for this command"}

#: OctoPrint job state (``/api/job`` ``state``, matched by prefix) -> PrinterStatus.state.
#: "Pausing", "Resuming" and "Cancelling" stay transient: OctoPrint ignores a resume until
#: the job is really "Paused", and a cancelling job may still move.
_STATES = {"printing": "printing", "paused": "paused", "pausing": "pausing", "resuming": "resuming",
           "cancelling": "cancelling", "operational": "idle", "finishing": "printing",
           "starting": "printing", "offline": "offline", "opening serial": "offline",
           "detecting serial": "offline", "connecting": "offline", "closed": "offline", "error": "error"}


def parse_octoprint_message(msg: Any, source: str = "octoprint") -> list:
    """Snapshot triggers in one decoded websocket message (its ``current`` logs only).

    OctoPrint opens every websocket connection with a ``history`` message: the last few hundred
    serial lines, earlier jobs' triggers among them. Those moments have passed (the head has
    moved on), so they are never triggers: a replayed ``layer=2`` of the previous job was
    photographed as this job's layer 2 before it started, and the real one was then dropped as
    a repeat. Anything that is not an object with ``logs`` lists of strings is ignored.
    """
    body = msg.get("current") if isinstance(msg, dict) else None
    logs = body.get("logs") if isinstance(body, dict) else None
    out = []
    for line in logs if isinstance(logs, list) else []:
        if isinstance(line, str) and line.startswith("Recv:"):
            trig = parse_line(line[5:], source=source)
            if trig is not None:
                out.append(trig)
    return out


def parse_job(job: Any, last_layer: int | None = None) -> PrinterStatus:
    """:class:`PrinterStatus` of an ``/api/job`` reply, every field type-checked.

    Raises
    ------
    PrinterError
        A field has the wrong type, or the completion is not a finite percentage.
    """
    where = "OctoPrint /api/job"
    st = text_field(job, "state", where, optional=False).lower()
    state = next((v for k, v in _STATES.items() if st.startswith(k)), "unknown")
    info = field(job, "job", dict, where) or {}
    file = field(info, "file", dict, where + " job") or {}
    name = text_field(file, "name", where + " job.file")
    progress = field(job, "progress", dict, where) or {}
    done = number_field(progress, "completion", where + " progress", 0.0, 100.0)
    return PrinterStatus(state, name, last_layer, None, None if done is None else done / 100.0)


class OctoPrintPrinter(Printer):
    """Connector for an OctoPrint server.

    Parameters
    ----------
    url : str
        ``http://host:port`` (``octoprint://`` is accepted; a ``?key=`` in it gives the key
        when ``api_key`` is not given, but the CLI reads keys from a key file, the environment
        or the job file, see :mod:`~layerwatch.monitor.printers.keys`).
    api_key : str, optional
    timeout_s : float
        HTTP timeout, s.
    push : bool
        Open the websocket and deliver triggers (``False``: REST only).
    """

    name = "octoprint"

    def __init__(self, url: str, api_key: str | None = None, *, timeout_s: float = 5.0, push: bool = True) -> None:
        super().__init__()
        bare, url_key = split_url_key(url)
        parts = urlsplit(bare)
        api_key = api_key or url_key
        if not api_key:
            raise PrinterError(f"OctoPrint needs an API key (Settings > API); set {ENV_VARS['octoprint']}, "
                               "pass --key-file FILE or put api_key in the job file's [host] section.")
        self.base = f"http://{parts.netloc}{parts.path.rstrip('/')}"
        self._http = httpx.Client(base_url=self.base, headers={"X-Api-Key": api_key}, timeout=timeout_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_layer: int | None = None
        self._ws_ready = threading.Event()
        #: ``listener(message)`` for every decoded websocket message (e.g. the M114 reply of parked.py)
        self.listeners: list = []
        self._warn = RateLimitedLog(log)
        if push:
            self._thread = threading.Thread(target=self._ws_loop, name="octoprint-ws", daemon=True)
            self._thread.start()

    # -- REST --------------------------------------------------------------
    def _req(self, method: str, path: str, **kw) -> Any:
        """Send a request; the validated JSON body for a GET or a login, else None (a command's reply is not used)."""
        r = http_request(self._http, method, path, printer="OctoPrint", credential="the API key",
                         auth_hint="copy the key from Settings > API", status_hints=_HINTS, **kw)
        if method == "GET" or path == "/api/login":
            return reply_json(r, f"OctoPrint {method} {path}")
        return None

    def status(self) -> PrinterStatus:
        return parse_job(self._req("GET", "/api/job"), self._last_layer)

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

    def cancel_object(self, obj: PrintObject) -> None:
        """``M486 P<id>`` through the command API: OctoPrint has no object-cancel API of its own, so the
        printer's firmware skips the object (Marlin/Prusa with ``M486`` labels in the file).

        Raises
        ------
        PrinterError
            The file has no ``M486`` labels (the firmware cannot know the object).
        """
        if obj.firmware_id is None:
            raise PrinterError(f"the job has no M486 labels, so the printer cannot skip {obj.name}; slice with "
                               "label objects on (OctoPrint has no object-cancel API).")
        self.send_gcode(f"M486 P{int(obj.firmware_id)}")

    def show_message(self, text: str) -> None:
        """``M117`` (the printer's display) and ``M118 A1 action:notification`` (the firmware echoes it as
        an action command: OctoPrint's bundled notification plugin shows it and lists it at
        ``GET /api/plugin/action_command_notification``)."""
        self.send_gcode([f"M117 {text}", f"M118 A1 action:notification {text}"])

    # -- push ----------------------------------------------------------------
    def _ws_loop(self) -> None:
        backoff = WS_RETRY_S[0]
        ws_url = "ws" + self.base[4:] + "/sockjs/websocket"
        while not self._stop.is_set():
            try:
                login = self._req("POST", "/api/login", json={"passive": True})
                user = text_field(login, "name", "OctoPrint /api/login", optional=False)
                session = text_field(login, "session", "OctoPrint /api/login", optional=False)
                with connect(ws_url, open_timeout=5, close_timeout=1, max_size=WS_MAX_FRAME_BYTES) as ws:
                    ws.send(json.dumps({"auth": f"{user}:{session}"}))
                    backoff = WS_RETRY_S[0]
                    while not self._stop.is_set():
                        try:
                            raw = ws.recv(timeout=0.5)
                        except TimeoutError:
                            continue
                        self._ws_ready.set()
                        self.handle_message(raw)
            except Exception as exc:  # noqa: BLE001 - reconnect on anything
                if self._stop.is_set():
                    return
                self._warn.warning("ws", "OctoPrint websocket: %s; reconnecting in %.1f s", exc, backoff)
                self._stop.wait(backoff)
                backoff = min(backoff * 2, WS_RETRY_S[1])

    def handle_message(self, raw: str | bytes) -> None:
        """Process one websocket message; a message that is not JSON or not of the expected shape is ignored."""
        try:
            msg = json.loads(raw)
        except (ValueError, RecursionError):
            self._warn.warning("frame", "OctoPrint websocket: a message that is not JSON was ignored")
            return
        for listener in list(self.listeners) if isinstance(msg, dict) else ():
            listener(msg)
        for trig in parse_octoprint_message(msg, self.name):
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
