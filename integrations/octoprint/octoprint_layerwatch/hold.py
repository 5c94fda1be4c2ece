"""Hold OctoPrint's job queue at a snapshot trigger until the frame is taken, with a time-out.

The prepared G-code (``layerwatch gcode prepare --profile octoprint``) parks the
head, sends ``M400`` and then the trigger ``@layerwatch snapshot layer=N z=Z``.
OctoPrint hands the ``@`` command to the ``octoprint.comm.protocol.atcommand.sending``
hook when its send loop reaches it, that is after the firmware acknowledged the
``M400`` (the send loop waits for the previous line's ``ok``; Marlin answers
``M400`` once every move is done): the head is parked and still.

:class:`SnapshotHold` then sets OctoPrint's *job on hold* flag
(``PrinterInterface.set_job_on_hold(True)``, OctoPrint >= 1.3): the comm layer
sends no further line of the printed file while it is set (user commands such
as a pause still go through). A worker thread takes the photo and clears the
flag as soon as the frame is in; a timer clears it after ``timeout_s`` whatever
the camera or the analysis do, so a dead camera or a hung layerwatch costs at
most ``timeout_s`` per layer and never stalls the print. The hook itself never
blocks OctoPrint's send thread. The printer is never paused and resumed for
the photo.

This module does not import OctoPrint: ``set_hold`` and ``take`` are plain callables.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

__all__ = ["HoldRecord", "SnapshotHold"]

log = logging.getLogger("octoprint.plugins.layerwatch.hold")


@dataclass
class HoldRecord:
    """One trigger and what the hold did.

    Attributes
    ----------
    layer : int
        Layer of the trigger.
    started : float
        ``time.time()`` when the trigger reached the send loop, s.
    held : bool
        The job was put on hold (False: another plugin held the lock, or the worker was busy).
    released : float or None
        ``time.time()`` when the hold was lifted, s.
    outcome : str
        ``"frame"`` (the frame was taken in time), ``"timeout"`` (lifted by the time-out),
        ``"skipped"`` (the previous layer's photo was still being taken: no hold, no photo),
        ``"ended"`` (the print ended during the hold) or ``"pending"``.
    """

    layer: int
    started: float
    held: bool
    released: float | None = None
    outcome: str = "pending"

    @property
    def held_ms(self) -> float | None:
        """How long the job was held, ms (``None`` while pending)."""
        return None if self.released is None else round((self.released - self.started) * 1000, 1)

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "held_ms": self.held_ms}


class SnapshotHold:
    """Hold the job from a trigger until ``take`` returns, at most ``timeout_s``.

    Parameters
    ----------
    set_hold : callable
        ``set_hold(on: bool) -> bool``: put the job on hold or lift it; returns whether it
        could (OctoPrint: ``lambda on: printer.set_job_on_hold(on, blocking=not on)``).
    take : callable
        ``take(trigger, expired) -> None``: take (and queue the analysis of) the photo;
        ``expired()`` tells whether the hold has already timed out (a frame taken after it
        may show the head moving and must not be analysed). Runs on a worker thread.
    timeout_s : float
        Longest hold per trigger, s (finite, > 0).
    keep : int
        Records kept for :meth:`records`.
    """

    def __init__(self, set_hold: Callable[[bool], bool], take: Callable[[Any, Callable[[], bool]], None],
                 timeout_s: float, *, keep: int = 500) -> None:
        if not (0 < float(timeout_s) < float("inf")):
            raise ValueError(f"hold time-out must be a finite number of seconds > 0, got {timeout_s!r}")
        self._set_hold, self._take, self.timeout_s = set_hold, take, float(timeout_s)
        self._lock = threading.Lock()
        self._busy = False
        self._current: HoldRecord | None = None
        #: ids of the records whose hold is being lifted (their outcome is set once it is)
        self._releasing: set[int] = set()
        self._records: deque[HoldRecord] = deque(maxlen=int(keep))

    def trigger(self, trigger: Any) -> HoldRecord:
        """Start the hold for ``trigger`` (``.layer``); returns at once (called on OctoPrint's send thread)."""
        now = time.time()
        with self._lock:
            if self._busy:  # the last photo is still being taken (dead camera): no second hold, no photo
                rec = HoldRecord(int(trigger.layer), now, held=False, released=now, outcome="skipped")
                self._records.append(rec)
                log.warning("layer %d: previous photo still pending, not held and not photographed", rec.layer)
                return rec
            self._busy = True
        try:
            held = bool(self._set_hold(True))
        except Exception:  # noqa: BLE001 - never let the hold break OctoPrint's send loop
            log.exception("could not put the job on hold")
            held = False
        rec = HoldRecord(int(trigger.layer), now, held=held)
        with self._lock:
            self._current = rec
            self._records.append(rec)
        timer = threading.Timer(self.timeout_s, self._release, (rec, "timeout"))
        timer.daemon = True
        timer.start()
        threading.Thread(target=self._run, args=(trigger, rec, timer), daemon=True,
                         name=f"layerwatch-photo-{rec.layer}").start()
        return rec

    def _run(self, trigger: Any, rec: HoldRecord, timer: threading.Timer) -> None:
        try:
            self._take(trigger, lambda: rec.outcome != "pending")
        except Exception:  # noqa: BLE001 - the hold must be lifted whatever happens
            log.exception("taking the photo of layer %d failed", rec.layer)
        finally:
            timer.cancel()
            self._release(rec, "frame")
            with self._lock:
                self._busy = False

    def _release(self, rec: HoldRecord, outcome: str) -> None:
        """Lift ``rec``'s hold once (the first of the frame, the timeout and the end), then record how it ended.

        The outcome is published after the hold is lifted, so whoever sees it no longer ``pending``
        (the photo thread's ``expired``, a caller polling the record) sees the job already released.
        """
        released = time.time()
        with self._lock:
            if rec.outcome != "pending" or id(rec) in self._releasing:
                return
            self._releasing.add(id(rec))
        if outcome == "timeout":
            log.warning("layer %d: no frame after %.1f s, the print goes on", rec.layer, self.timeout_s)
        if rec.held:
            try:
                self._set_hold(False)
            except Exception:  # noqa: BLE001
                log.exception("could not lift the hold")
        with self._lock:
            rec.outcome, rec.released = outcome, released
            self._releasing.discard(id(rec))
            if self._current is rec:
                self._current = None

    def end(self) -> None:
        """Lift a pending hold (the print ended or was cancelled)."""
        with self._lock:
            rec = self._current
        if rec is not None:
            self._release(rec, "ended")

    def records(self) -> list[dict[str, Any]]:
        """The kept hold records, oldest first, as dicts (``held_ms`` included)."""
        with self._lock:
            return [r.as_dict() for r in self._records]
