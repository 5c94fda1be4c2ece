"""The small interface every printer connector implements.

A connector reports the printer's state, pauses/resumes/cancels the job,
sends G-code, and delivers the snapshot triggers that
:func:`layerwatch.gcode.postprocess.insert_snapshots` put into the G-code
(``@layerwatch snapshot layer=<n> z=<z>``, ``M118 E1 layerwatch snapshot ...``
or the Klipper macro's ``layerwatch snapshot layer=<n> z=<z>`` response).
"""

from __future__ import annotations

import json
import re
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import httpx

from layerwatch.errors import PrinterError
from layerwatch.monitor.printers.replies import MAX_REPLY_BYTES, read_capped

if TYPE_CHECKING:
    import httpx

    from layerwatch.gcode.objects import PrintObject

__all__ = ["PrinterStatus", "SnapshotTrigger", "Printer", "parse_trigger", "parse_signal", "parse_line", "http_request", "error_detail", "TRANSIENT_STATES", "WS_RETRY_S",
           "WS_MAX_FRAME_BYTES"]

#: websocket reconnect wait of the connectors: first, largest (s); doubles per failed attempt.
#: Capped low so that triggers flow again within seconds after a host restart.
WS_RETRY_S = (0.5, 5.0)

#: largest websocket message the connectors accept, bytes (OctoPrint's history message is the largest)
WS_MAX_FRAME_BYTES = 4 << 20

#: states a job passes through on its way to paused / printing / cancelled
TRANSIENT_STATES = frozenset({"pausing", "resuming", "cancelling"})

_TRIGGER = re.compile(
    r"(?:@layerwatch\s+snapshot|layerwatch\s+snapshot|LAYERWATCH_SNAPSHOT)\s+"
    r"layer=(?P<layer>-?\d+)\s+z=(?P<z>[-+0-9.eE]+)",
    re.IGNORECASE,
)


def parse_trigger(line: str, source: str = "") -> SnapshotTrigger | None:
    """Recognise one snapshot trigger line (any of the inserted formats).

    Parameters
    ----------
    line : str
        A G-code line, host command, echo or gcode response.
    source : str
        Where the line came from (``"virtual"``, ``"octoprint"``...).

    Returns
    -------
    SnapshotTrigger or None
        ``None`` when the line is not a trigger (comments never are).
    """
    text = line.split(";", 1)[0] if not line.lstrip().startswith(";") else ""
    m = _TRIGGER.search(text)
    if m is None:
        return None
    try:
        return SnapshotTrigger(layer=int(m["layer"]), z=float(m["z"]), source=source)
    except ValueError:
        return None


_SIGNAL = re.compile(r"layerwatch\s+(?P<signal>quiet|watch)\b(?:\s+s=(?P<s>\d+(?:\.\d+)?))?", re.IGNORECASE)
#: longest quiet period a signal may ask for, s (detection resumes by itself after it)
QUIET_MAX_S = 3600.0
#: quiet period of a ``layerwatch quiet`` signal without ``s=``, s
QUIET_DEFAULT_S = 600.0


def parse_signal(line: str, source: str = "") -> SnapshotTrigger | None:
    """Recognise a detection signal of a macro or queue script (not a comment).

    ``layerwatch quiet [s=<seconds>]`` (``M118 E1 ...`` on Marlin/OctoPrint, ``RESPOND MSG="..."`` on
    Klipper) suspends detection for ``s`` seconds (default :data:`QUIET_DEFAULT_S`, at most
    :data:`QUIET_MAX_S`) or until ``layerwatch watch``, e.g. while a farm queue clears the bed.

    Returns
    -------
    SnapshotTrigger or None
        With ``signal`` ``"quiet"`` or ``"watch"``, ``layer`` -1 and ``z`` the quiet seconds (0 for watch).
    """
    text = line.split(";", 1)[0] if not line.lstrip().startswith(";") else ""
    m = _SIGNAL.search(text)
    if m is None or _TRIGGER.search(text):
        return None
    signal = m["signal"].lower()
    secs = 0.0 if signal == "watch" else min(float(m["s"]) if m["s"] else QUIET_DEFAULT_S, QUIET_MAX_S)
    return SnapshotTrigger(layer=-1, z=secs, source=source, signal=signal)


def parse_line(line: str, source: str = "") -> SnapshotTrigger | None:
    """A snapshot trigger (:func:`parse_trigger`) or a detection signal (:func:`parse_signal`) in ``line``."""
    return parse_trigger(line, source) or parse_signal(line, source)


def error_detail(body: str, limit: int = 160) -> str:
    """The human part of an HTTP error body, one line.

    Moonraker answers ``{"error": {"code", "message", "traceback"}}``, OctoPrint
    ``{"error": "..."}`` or a short HTML/text page; the message is kept, a
    traceback never.

    Parameters
    ----------
    body : str
        Response text.
    limit : int
        Maximum length of the result, characters.
    """
    text = body.strip()
    try:
        data = json.loads(text)
    except ValueError:
        data = None
    if isinstance(data, dict):
        err = data.get("error", data.get("message"))
        if isinstance(err, dict):
            err = err.get("message") or err.get("error")
        if isinstance(err, str) and err.strip():
            text = err
    text = re.sub(r"<[^>]+>", " ", text)  # HTML error pages
    text = " ".join(text.split())
    return text[:limit] or "(empty body)"


def http_request(http: httpx.Client, method: str, path: str, *, printer: str, credential: str,
                 auth_hint: str, status_hints: Mapping[int, str] | None = None,
                 max_bytes: int = MAX_REPLY_BYTES, **kw: Any) -> httpx.Response:
    """Send one request of a printer connector and turn every failure into a :class:`PrinterError`.

    Parameters
    ----------
    http : httpx.Client
        Client with ``base_url`` set.
    method, path : str
        HTTP method and path (``"POST"``, ``"/api/job"``).
    printer : str
        Host software name for messages (``"OctoPrint"``, ``"Moonraker"``).
    credential : str
        What a 401/403 refused (``"the API key"``, ``"the request"``).
    auth_hint : str
        How to fix a 401/403 (one clause).
    status_hints : mapping of int to str, optional
        Extra explanation per status code (OctoPrint's 409: not connected / not printing).
    max_bytes : int
        Largest body accepted, bytes (:data:`~layerwatch.monitor.printers.replies.MAX_REPLY_BYTES`).
    **kw
        Passed to :meth:`httpx.Client.build_request` (``params``, ``json``...).

    Returns
    -------
    httpx.Response
        A response with status < 400.

    Raises
    ------
    PrinterError
        Unreachable host (connection refused, timeout, reset mid-body...), a body
        over ``max_bytes``, refused credentials, or any status >= 400 (with the
        server's own message, never its traceback).
    """
    base = str(http.base_url).rstrip("/")
    where = f"{printer} {method} {path}"
    try:
        r = http.send(http.build_request(method, path, **kw), stream=True)
        try:
            body = read_capped(r, max_bytes, where)
        finally:
            r.close()
    except (httpx.HTTPError, OSError) as exc:  # OSError: a socket error httpx did not wrap
        raise PrinterError(f"{printer} at {base} unreachable ({type(exc).__name__}); "
                           "check host, port and that it runs.") from exc
    # the body is decoded already (gzip...): keep the headers that still describe it
    headers = [(k, v) for k, v in r.headers.items() if k.lower() not in ("content-encoding", "content-length")]
    r = httpx.Response(r.status_code, headers=headers, content=body, request=r.request)
    if r.status_code < 400:
        return r
    detail = error_detail(r.text)
    if r.status_code in (401, 403):
        raise PrinterError(f"{printer} at {base} refused {credential} (HTTP {r.status_code}: {detail}); {auth_hint}.")
    hint = (status_hints or {}).get(r.status_code)
    if hint:
        raise PrinterError(f"{printer} refused {method} {path} (HTTP {r.status_code}: {detail}); {hint}.")
    raise PrinterError(f"{printer} {method} {path} failed with HTTP {r.status_code}: {detail}")


@dataclass(frozen=True)
class PrinterStatus:
    """What the printer is doing.

    Attributes
    ----------
    state : str
        ``"idle"``, ``"printing"``, ``"paused"``, ``"cancelled"``, ``"finished"``,
        ``"error"``, ``"offline"`` or ``"unknown"`` (a state the connector does not know,
        never taken for the end of the job); or a transient ``"pausing"``, ``"resuming"``,
        ``"cancelling"`` (OctoPrint) while the host is between two of those: a
        ``"pausing"`` job is not paused yet (OctoPrint ignores a resume then).
    file : str or None
        Name of the job's G-code file.
    layer : int or None
        Last layer index reported by a trigger (0-based).
    z : float or None
        Current Z, mm.
    progress : float or None
        Job progress in [0, 1].
    """

    state: str
    file: str | None = None
    layer: int | None = None
    z: float | None = None
    progress: float | None = None

    @property
    def transient(self) -> bool:
        """True while the host is pausing, resuming or cancelling (wait for the state it goes to)."""
        return self.state in TRANSIENT_STATES


@dataclass(frozen=True)
class SnapshotTrigger:
    """One "layer done, take the photo now" event.

    Attributes
    ----------
    layer : int
        0-based layer index from the trigger line.
    z : float
        Layer top Z, mm.
    source : str
        Connector name.
    time : float
        ``time.monotonic()`` when the connector saw it, s.
    signal : str
        ``""`` for a snapshot trigger; ``"quiet"`` / ``"watch"`` for a detection signal
        (:func:`parse_signal`: ``layer`` -1, ``z`` the quiet seconds).
    """

    layer: int
    z: float
    source: str = ""
    time: float = field(default_factory=time.monotonic)
    signal: str = ""


class Printer(ABC):
    """Abstract printer connector.

    Triggers can be consumed by polling (:meth:`poll_triggers`) or pushed to
    callbacks registered with :meth:`subscribe`; the base class keeps both.
    """

    name = "printer"

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pending: list[SnapshotTrigger] = []
        self._callbacks: list[Callable[[SnapshotTrigger], None]] = []

    # -- trigger delivery (shared) -------------------------------------
    def _emit(self, trigger: SnapshotTrigger) -> None:
        with self._lock:
            self._pending.append(trigger)
            callbacks = list(self._callbacks)
        for cb in callbacks:
            cb(trigger)

    def poll_triggers(self) -> list[SnapshotTrigger]:
        """Return and forget the triggers seen since the last call, oldest first."""
        with self._lock:
            out, self._pending = self._pending, []
        return out

    def subscribe(self, callback: Callable[[SnapshotTrigger], None]) -> None:
        """Call ``callback(trigger)`` for every future trigger (from the connector's thread)."""
        with self._lock:
            self._callbacks.append(callback)

    # -- driving -----------------------------------------------------------
    @property
    def needs_stepping(self) -> bool:
        """True when the caller advances the job with :meth:`step_to_next_trigger` (a replay nobody started).

        A real host prints on its own and pushes triggers: ``False``.
        """
        return False

    def step_to_next_trigger(self) -> SnapshotTrigger | None:
        """Advance a caller-driven printer to its next trigger (see :attr:`needs_stepping`)."""
        raise NotImplementedError(f"{type(self).__name__} prints on its own; it is not stepped")

    # -- control ---------------------------------------------------------
    @abstractmethod
    def status(self) -> PrinterStatus:
        """Current state; raises :class:`~layerwatch.errors.PrinterError` when unreachable."""

    @abstractmethod
    def pause(self) -> None:
        """Ask the printer to pause the job."""

    @abstractmethod
    def resume(self) -> None:
        """Resume a paused job."""

    @abstractmethod
    def cancel(self) -> None:
        """Cancel the job."""

    @abstractmethod
    def send_gcode(self, lines: str | Iterable[str]) -> None:
        """Send G-code line(s) to the printer."""

    def cancel_object(self, obj: PrintObject) -> None:
        """Skip one object of the running job from now on (see :mod:`layerwatch.gcode.objects`).

        Raises
        ------
        PrinterError
            This host cannot skip objects, or the job does not label them the way its firmware needs.
        """
        raise PrinterError(f"{type(self).__name__} cannot cancel a single object; pause instead.")

    def show_message(self, text: str) -> None:  # noqa: B027 - optional: hosts without a display show nothing
        """Show one short line (printable ASCII) where the user looks: the printer's display, the host's UI."""

    def photo_done(self, trigger: SnapshotTrigger) -> None:
        """Tell the printer the photo of ``trigger`` was taken (or could not be), so a hold ends now.

        The default does nothing: a printer that dwells for a fixed time at the park spot
        (the ``octoprint`` profile's ``G4``) needs no answer. Klipper's
        ``LAYERWATCH_SNAPSHOT`` hold waits for one (:class:`MoonrakerPrinter`).
        """
        return None

    def close(self) -> None:
        """Release connections and threads (idempotent)."""
        return None

    def __enter__(self) -> Printer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
