"""Jobs pick themselves up: see a print start on the host, fetch its G-code, hand it to a monitor.

:class:`JobWatcher` polls the printer host (:mod:`layerwatch.monitor.hosts`: OctoPrint
``/api/job``, Moonraker ``print_stats``) for the current job. When a job starts it downloads
that job's own G-code through the host's file API, checks that the file carries layerwatch's
snapshot trigger (:func:`check_prepared`), and hands it to a monitor; a job without the
trigger is reported with the exact ``layerwatch gcode prepare`` command and not analysed.
Then it waits for the next job. A host that cannot be reached or answers nonsense is logged
and retried with a capped back-off; it never stops the service.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from layerwatch.errors import LayerwatchError, PrinterError
from layerwatch.gcode.bgcode import decode_bgcode
from layerwatch.monitor.hosts import MAX_GCODE_BYTES, JobHost, PrintJob
from layerwatch.monitor.printers.base import Printer

__all__ = ["find_triggers", "check_prepared", "JobNotPrepared", "JobWatcher", "HOST_PROFILE", "ACTIVE"]

log = logging.getLogger("layerwatch.monitor.jobs")

#: the ``gcode prepare`` profile whose trigger each host's connector sees
HOST_PROFILE = {"octoprint": "octoprint", "moonraker": "klipper"}

#: host states during which a job is running
ACTIVE = frozenset({"printing", "paused", "pausing", "resuming", "cancelling"})

# A trigger as the firmware/host sees it: not inside a comment (the whole line is checked).
_TRIGGER = re.compile(rb"(?im)^[ \t]*(?:N\d+[ \t]+)?(?P<cmd>@layerwatch[ \t]+snapshot|M118[^;\n]*?layerwatch[ \t]+snapshot"
                      rb"|RESPOND[^;\n]*?layerwatch[ \t]+snapshot|LAYERWATCH_SNAPSHOT)[ \t]+layer=(?P<layer>-?\d+)")

#: ``@layerwatch`` host commands reach only OctoPrint plugins and never the firmware, so neither
#: connector sees them; every other trigger comes back from the firmware (M118 echo, Klipper's
#: RESPOND; even Marlin's "Unknown command" echo of the Klipper macro carries the trigger text)
_HOST_COMMAND = b"LAYERWATCH"


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
