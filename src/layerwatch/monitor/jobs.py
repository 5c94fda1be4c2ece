"""Jobs pick themselves up: see a print start on the host, fetch its G-code, hand it to a monitor.

:class:`JobWatcher` polls the printer host (OctoPrint ``GET /api/job``,
Moonraker ``print_stats``) for the current job. When a job starts it
downloads that job's own G-code through the host's file API (OctoPrint
``/downloads/files/local/<path>``, Moonraker ``/server/files/gcodes/<path>``),
checks that the file carries layerwatch's snapshot trigger
(:func:`check_prepared`), and hands it to a monitor; a job without the
trigger is reported with the exact ``layerwatch gcode prepare`` command and
not analysed. Then it waits for the next job.

Every reply is validated before use: HTTP status (through
:func:`~layerwatch.monitor.printers.base.http_request`), content type, a size
cap while streaming the download, and the JSON shape and types of the job
status. A host that cannot be reached or answers nonsense is logged and
retried with a capped back-off; it never stops the service.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import quote

import httpx
import numpy as np

from layerwatch.errors import LayerwatchError, PrinterError
from layerwatch.monitor.printers.base import Printer, error_detail, http_request

__all__ = ["PrintJob", "JobHost", "find_triggers", "OctoPrintJobs", "MoonrakerJobs", "job_host", "check_prepared",
           "JobNotPrepared", "JobWatcher", "MAX_GCODE_BYTES", "HOST_PROFILE"]

log = logging.getLogger("layerwatch.monitor.jobs")

#: largest G-code download accepted, bytes (a 500 MB file is an hours-long print of a big part)
MAX_GCODE_BYTES = 512 * 1024 * 1024

#: the ``gcode prepare`` profile whose trigger each host's connector sees
HOST_PROFILE = {"octoprint": "octoprint", "moonraker": "klipper"}

#: host states during which a job is running
ACTIVE = frozenset({"printing", "paused", "pausing", "resuming", "cancelling"})

#: content types a G-code download may have (hosts send G-code as text or as bytes)
_GCODE_TYPES = ("text/plain", "text/x-gcode", "application/octet-stream", "application/x-gcode", "text/x.gcode")

# A trigger as the firmware/host sees it: not inside a comment (the whole line is checked).
_TRIGGER = re.compile(rb"(?im)^[ \t]*(?:N\d+[ \t]+)?(?P<cmd>@layerwatch[ \t]+snapshot|M118[^;\n]*?layerwatch[ \t]+snapshot"
                      rb"|RESPOND[^;\n]*?layerwatch[ \t]+snapshot|LAYERWATCH_SNAPSHOT)[ \t]+layer=(?P<layer>-?\d+)")

#: ``@layerwatch`` host commands reach only OctoPrint plugins and never the firmware, so neither
#: connector sees them; every other trigger comes back from the firmware (M118 echo, Klipper's
#: RESPOND; even Marlin's "Unknown command" echo of the Klipper macro carries the trigger text)
_HOST_COMMAND = b"LAYERWATCH"


@dataclass(frozen=True)
class PrintJob:
    """The job a host is printing.

    Attributes
    ----------
    host : str
        ``"octoprint"`` or ``"moonraker"``.
    path : str
        File path in the host's storage (OctoPrint ``local`` origin, Moonraker ``gcodes`` root).
    origin : str
        Storage (``"local"``, ``"sdcard"``, ``"gcodes"``).
    size : int or None
        Size the host reports, bytes.
    """

    host: str
    path: str
    origin: str = "local"
    size: int | None = None

    @property
    def name(self) -> str:
        """File name without folders."""
        return self.path.rsplit("/", 1)[-1]


class JobNotPrepared(LayerwatchError):
    """The job's G-code carries no snapshot trigger the host can deliver; the message says how to prepare it."""


def find_triggers(data: bytes) -> list[tuple[int, int, bytes]]:
    """Every snapshot trigger line of ASCII G-code ``data``.

    Returns
    -------
    list of (int, int, bytes)
        ``(line, layer, command)``: 1-based line number, the trigger's layer, and its command
        (``b"M118"``, ``b"LAYERWATCH_SNAPSHOT"``, ``b"RESPOND"`` or ``b"layerwatch"`` for the
        ``@layerwatch`` host command), in file order.
    """
    matches = list(_TRIGGER.finditer(data))
    if not matches:
        return []
    newlines = np.flatnonzero(np.frombuffer(data, np.uint8) == 10)
    lines = np.searchsorted(newlines, [m.start("cmd") for m in matches]) + 1
    return [(int(n), int(m["layer"]), m["cmd"].split()[0].upper().lstrip(b"@"))
            for n, m in zip(lines, matches, strict=True)]


def check_prepared(data: bytes, host: str, name: str) -> int:
    """Count the snapshot triggers in ``data`` that ``host``'s connector can see.

    Parameters
    ----------
    data : bytes
        The job's G-code (ASCII; a binary ``.bgcode`` is decoded first).
    host : str
        ``"octoprint"`` or ``"moonraker"``.
    name : str
        File name for the message.

    Returns
    -------
    int
        Number of trigger lines (> 0).

    Raises
    ------
    JobNotPrepared
        No trigger at all, or only ``@layerwatch`` host commands (they reach OctoPrint plugins,
        never the firmware, so no connector sees them). The message names the
        ``layerwatch gcode prepare`` command for this host.
    """
    if data[:4] == b"GCDE":
        from layerwatch.gcode.bgcode import decode_bgcode

        data = decode_bgcode(data, name)
    found = [cmd for _, _, cmd in find_triggers(data)]
    usable = [c for c in found if c != _HOST_COMMAND]
    if usable:
        return len(usable)
    profile = HOST_PROFILE[host]
    fix = (f"prepare it with `layerwatch gcode prepare {name} --profile {profile} -o {name}` "
           f"and print the prepared file")
    if found:
        raise JobNotPrepared(f"{name}: its snapshot triggers are @layerwatch host commands only, which never reach "
                             f"layerwatch through {host}; {fix}.")
    raise JobNotPrepared(f"{name}: no layerwatch snapshot trigger in the file, so no layer can be photographed; "
                         f"{fix}.")


class JobHost(ABC):
    """What the watcher asks of a printer host: the current job and its file.

    Parameters
    ----------
    http : httpx.Client
        The connector's client (``base_url`` and credentials set).
    """

    kind = "host"
    printer_name = "host"

    def __init__(self, http: httpx.Client) -> None:
        self.http = http

    def _json(self, method: str, path: str, **kw: Any) -> Any:
        r = http_request(self.http, method, path, printer=self.printer_name, credential="the request",
                         auth_hint="check the API key in the printer URL", **kw)
        if "json" not in r.headers.get("content-type", ""):
            raise PrinterError(f"{self.printer_name} {path} answered {r.headers.get('content-type') or 'no content type'}"
                               f", not JSON ({error_detail(r.text, 60)}); check the printer URL points at "
                               f"{self.printer_name}.")
        try:
            return r.json()
        except ValueError:
            raise PrinterError(f"{self.printer_name} {path} answered invalid JSON; check the printer URL.") from None

    @abstractmethod
    def current(self) -> tuple[str, PrintJob | None]:
        """The host's state (``printing``, ``paused``, ``idle``...) and its job (``None`` when there is none)."""

    @abstractmethod
    def download_path(self, job: PrintJob) -> str:
        """URL path of the job's file."""

    def position(self) -> tuple[float, float, float] | None:
        """The head's position as the printer reports it (G-code coordinates, mm), or ``None`` if it cannot tell."""
        return None

    def last_outcome(self, job: PrintJob) -> str | None:
        """How ``job``, which just left the host, ended (``"done"``, ``"cancelled"``) where the state alone says idle."""
        return None

    def download(self, job: PrintJob, max_bytes: int = MAX_GCODE_BYTES) -> bytes:
        """The job's G-code, streamed with a size cap.

        Raises
        ------
        PrinterError
            Unreachable host, HTTP error, a web page or JSON instead of G-code, an empty file, a
            file larger than ``max_bytes`` or a body shorter than its ``Content-Length``.
        """
        path = self.download_path(job)
        where = f"{self.printer_name} {path}"
        try:
            with self.http.stream("GET", path) as r:
                if r.status_code >= 400:
                    r.read()
                    raise PrinterError(f"{where} failed with HTTP {r.status_code}: {error_detail(r.text)}; "
                                       "check that the file still exists on the host.")
                ctype = r.headers.get("content-type", "").split(";")[0].strip().lower()
                if ctype and not ctype.startswith(_GCODE_TYPES):
                    raise PrinterError(f"{where} sent {ctype}, not G-code; check the printer URL.")
                declared = r.headers.get("content-length")
                if declared is not None and (not declared.isdigit() or int(declared) > max_bytes):
                    raise PrinterError(f"{where}: file of {declared} bytes is over the {max_bytes} byte limit.")
                chunks, total = [], 0
                for chunk in r.iter_bytes():
                    total += len(chunk)
                    if total > max_bytes:
                        raise PrinterError(f"{where}: file larger than the {max_bytes} byte limit.")
                    chunks.append(chunk)
        except httpx.HTTPError as exc:
            raise PrinterError(f"{where}: download failed ({type(exc).__name__}); check the host.") from exc
        if declared is not None and total != int(declared):
            raise PrinterError(f"{where}: got {total} of {declared} bytes; the download was cut short.")
        if total == 0:
            raise PrinterError(f"{where}: the file is empty.")
        return b"".join(chunks)


def _field(obj: Any, key: str, kinds: type | tuple[type, ...], where: str, optional: bool = True) -> Any:
    """``obj[key]`` checked against ``kinds`` (``None`` allowed when ``optional``)."""
    if not isinstance(obj, dict):
        raise PrinterError(f"{where}: expected a JSON object, got {type(obj).__name__}.")
    value = obj.get(key)
    if value is None and optional:
        return None
    if not isinstance(value, kinds) or isinstance(value, bool):
        raise PrinterError(f"{where}: field {key!r} is {type(value).__name__}, not {kinds}; is this the right host?")
    return value


class OctoPrintJobs(JobHost):
    """OctoPrint's ``/api/job`` and ``/downloads/files/local/<path>``."""

    kind = printer_name = "octoprint"

    def current(self) -> tuple[str, PrintJob | None]:
        from layerwatch.monitor.printers.octoprint import _STATES

        body = self._json("GET", "/api/job")
        text = str(_field(body, "state", str, "OctoPrint /api/job", optional=False)).lower()
        state = next((v for k, v in _STATES.items() if text.startswith(k)), "idle")
        job = _field(body, "job", dict, "OctoPrint /api/job")
        file = _field(job, "file", dict, "OctoPrint /api/job job") if job else None
        path = _field(file, "path", str, "OctoPrint /api/job job.file") if file else None
        if not path:
            return state, None
        origin = _field(file, "origin", str, "OctoPrint /api/job job.file") or "local"
        size = _field(file, "size", int, "OctoPrint /api/job job.file")
        return state, PrintJob("octoprint", path, origin, size)

    def last_outcome(self, job: PrintJob) -> str | None:
        """OctoPrint goes back to "Operational" after both; the file's print record (``prints.last.success``) tells.

        OctoPrint records a cancelled and a failed print alike (``success: false``): both give ``"cancelled"``.
        """
        if job.origin != "local":
            return None
        body = self._json("GET", "/api/files/local/" + quote(job.path, safe="/"))
        prints = _field(body, "prints", dict, "OctoPrint file record")
        last = _field(prints, "last", dict, "OctoPrint file record prints") if prints else None
        ok = last.get("success") if last else None
        return None if not isinstance(ok, bool) else ("done" if ok else "cancelled")

    def download_path(self, job: PrintJob) -> str:
        if job.origin != "local":
            raise JobNotPrepared(f"{job.name} is printed from the printer's SD card, which OctoPrint cannot read back; "
                                 "upload the prepared file to OctoPrint and print it from there.")
        return "/downloads/files/local/" + quote(job.path, safe="/")


class MoonrakerJobs(JobHost):
    """Moonraker's ``print_stats`` and ``/server/files/gcodes/<path>``."""

    kind = printer_name = "moonraker"

    def current(self) -> tuple[str, PrintJob | None]:
        from layerwatch.monitor.printers.moonraker import _STATES

        body = self._json("GET", "/printer/objects/query", params={"print_stats": "state,filename"})
        status = _field(_field(body, "result", dict, "Moonraker objects query", optional=False),
                        "status", dict, "Moonraker objects query result", optional=False)
        stats = _field(status, "print_stats", dict, "Moonraker status", optional=False)
        state = _STATES.get(str(_field(stats, "state", str, "Moonraker print_stats", optional=False)), "idle")
        path = _field(stats, "filename", str, "Moonraker print_stats")
        return state, (PrintJob("moonraker", path, "gcodes") if path else None)

    def download_path(self, job: PrintJob) -> str:
        return "/server/files/gcodes/" + quote(job.path, safe="/")

    def position(self) -> tuple[float, float, float]:
        """Klipper's ``gcode_move.gcode_position`` (X, Y, Z in G-code coordinates, mm).

        Raises
        ------
        PrinterError
            Unreachable host, or a reply without three finite numbers.
        """
        body = self._json("GET", "/printer/objects/query", params={"gcode_move": "gcode_position"})
        status = _field(_field(body, "result", dict, "Moonraker objects query", optional=False),
                        "status", dict, "Moonraker objects query result", optional=False)
        pos = _field(_field(status, "gcode_move", dict, "Moonraker status", optional=False),
                     "gcode_position", list, "Moonraker gcode_move", optional=False)
        try:
            xyz = tuple(float(v) for v in pos[:3])
        except (TypeError, ValueError):
            xyz = ()
        if len(xyz) != 3 or not all(np.isfinite(xyz)):
            raise PrinterError(f"Moonraker gcode_move.gcode_position is {pos!r}, not a position; is Klippy ready?")
        return xyz  # type: ignore[return-value]


def job_host(printer: Printer) -> JobHost:
    """The :class:`JobHost` for a connector (uses the connector's HTTP client and credentials).

    Raises
    ------
    ConfigError
        The printer is not an OctoPrint or Moonraker connector (the virtual printer has no host).
    """
    from layerwatch.errors import ConfigError

    cls = {"octoprint": OctoPrintJobs, "moonraker": MoonrakerJobs}.get(printer.name)
    http = getattr(printer, "_http", None)
    if cls is None or http is None:
        raise ConfigError(f"--printer {printer.name} has no job host to follow; use octoprint://... or moonraker://..., "
                          "or give the job with --gcode.")
    return cls(http)


class _Runner:
    """A monitor run in its own thread (``run()``, ``stop_event``, ``close`` as on :class:`Monitor`)."""

    def __init__(self, monitor: Any) -> None:
        self.monitor = monitor
        self.report = None
        self.thread = threading.Thread(target=self._run, name="layerwatch-job", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self.report = self.monitor.run(poll_s=0.2)
        except Exception:  # noqa: BLE001 - a monitor bug ends this job, never the service
            log.exception("monitor of the job failed")

    def alive(self) -> bool:
        return self.thread.is_alive()


class JobWatcher:
    """Pick up every job the host starts, one after the other.

    Parameters
    ----------
    host : JobHost
        Where jobs are seen and downloaded.
    start : callable
        ``start(job, gcode) -> Monitor``: builds the monitor of one job (pipeline, camera,
        history row) from the downloaded G-code; may raise :class:`LayerwatchError` (unusable
        G-code), which rejects the job.
    reject : callable, optional
        ``reject(job, message)``: a job that is not analysed (no trigger, download failed); the
        message says why and what to do. Logged either way.
    poll_s : float
        Host poll interval, s.
    max_jobs : int, optional
        Stop after this many jobs were handled (analysed or rejected); ``None``: run until
        :attr:`stop_event` is set.
    end_grace_s : float
        After the host shows the job ended, the monitor has this long to finish its last layers
        on its own before it is stopped (it stops by itself once it analysed a layer), s.
    max_backoff_s : float
        Largest wait between polls of an unreachable host, s.
    max_bytes : int
        Size cap of a G-code download, bytes.
    """

    def __init__(self, host: JobHost, start: Callable[[PrintJob, bytes], Any],
                 reject: Callable[[PrintJob, str], None] | None = None, *,
                 on_end: Callable[[PrintJob, Any], None] | None = None, poll_s: float = 1.0,
                 max_jobs: int | None = None, end_grace_s: float = 10.0, max_backoff_s: float = 30.0,
                 max_bytes: int = MAX_GCODE_BYTES) -> None:
        self.host, self.start, self.reject, self.on_end = host, start, reject, on_end
        self.poll_s, self.max_jobs, self.end_grace_s = float(poll_s), max_jobs, float(end_grace_s)
        self.max_backoff_s, self.max_bytes = float(max_backoff_s), int(max_bytes)
        self.stop_event = threading.Event()
        #: one entry per job handled: ``(job, outcome)``; outcome ``"not prepared"``, ``"error"`` or the monitor's
        self.handled: list[tuple[PrintJob, str]] = []
        self._done: PrintJob | None = None  # the job handled last, while the host still runs it

    def run(self) -> list[tuple[PrintJob, str]]:
        """Watch until :attr:`stop_event` is set or ``max_jobs`` jobs were handled; returns :attr:`handled`."""
        backoff = self.poll_s
        while not self.stop_event.is_set():
            try:
                state, job = self.host.current()
            except PrinterError as exc:
                log.warning("job host: %s; retrying in %.1f s", exc, backoff)
                self.stop_event.wait(backoff)
                backoff = min(2 * backoff, self.max_backoff_s)
                continue
            backoff = self.poll_s
            if state not in ACTIVE or job is None:
                self._done = None  # that job is over: the next one is new
            elif self._done is None or job.path != self._done.path:
                log.info("job started on %s: %s", self.host.kind, job.path)
                self.handled.append((job, self._handle(job)))
                self._done = job
                if self.max_jobs is not None and len(self.handled) >= self.max_jobs:
                    break
                log.info("waiting for the next job on %s", self.host.kind)
            self.stop_event.wait(self.poll_s)
        return self.handled

    def _fetch(self, job: PrintJob) -> bytes:
        """Download with up to three attempts (a host busy starting the print may time out once)."""
        for attempt in range(3):
            try:
                return self.host.download(job, self.max_bytes)
            except PrinterError as exc:
                if attempt == 2 or self.stop_event.is_set():
                    raise
                log.warning("download of %s failed (%s); retrying", job.path, exc)
                self.stop_event.wait(self.poll_s * (attempt + 1))
        raise AssertionError("unreachable")

    def _refuse(self, job: PrintJob, message: str, outcome: str) -> str:
        log.warning("job %s not analysed: %s", job.path, message)
        if self.reject is not None:
            try:
                self.reject(job, message)
            except LayerwatchError as exc:
                log.warning("could not record the rejected job: %s", exc)
        return outcome

    def _handle(self, job: PrintJob) -> str:
        try:
            data = self._fetch(job)
            n = check_prepared(data, self.host.kind, job.name)
        except JobNotPrepared as exc:
            return self._refuse(job, str(exc), "not prepared")
        except LayerwatchError as exc:
            return self._refuse(job, f"could not fetch {job.name}: {exc}", "error")
        log.info("downloaded %s: %d bytes, %d snapshot triggers", job.path, len(data), n)
        try:
            monitor = self.start(job, data)
        except LayerwatchError as exc:
            return self._refuse(job, str(exc), "error")
        runner = _Runner(monitor)
        ended_at: float | None = None
        while runner.alive():
            runner.thread.join(self.poll_s)
            if self.stop_event.is_set():
                monitor.stop_event.set()
                continue
            try:
                state, cur = self.host.current()
            except PrinterError:
                continue  # the monitor reports outages itself
            if state in ACTIVE and cur is not None and cur.path == job.path:
                ended_at = None
            elif ended_at is None:
                ended_at = time.monotonic()
            elif time.monotonic() - ended_at > self.end_grace_s:
                monitor.stop_event.set()  # the job is over but the monitor saw no layer: stop it
        _forget_job(monitor.printer)
        if runner.report is not None and runner.report.outcome == "idle":  # OctoPrint: finished or cancelled?
            try:
                runner.report.outcome = self.host.last_outcome(job) or "idle"
            except PrinterError as exc:
                log.warning("outcome of %s unknown: %s", job.path, exc)
        if self.on_end is not None:
            try:
                self.on_end(job, monitor)
            except LayerwatchError as exc:
                log.warning("after job %s: %s", job.path, exc)
        report = runner.report
        return "error" if report is None else report.outcome


def _forget_job(printer: Printer) -> None:
    """Drop triggers left from the job that ended, and the connector's last-layer memory.

    The connectors drop a trigger whose layer equals the previous one (websocket replays);
    without this, the next job's first layer would be dropped when the last job ended on it.
    """
    printer.poll_triggers()
    if hasattr(printer, "_last_layer"):
        printer._last_layer = None
