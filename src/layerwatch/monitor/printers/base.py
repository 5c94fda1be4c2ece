"""The small interface every printer connector implements.

A connector reports the printer's state, pauses/resumes/cancels the job,
sends G-code, and delivers the snapshot triggers that
:func:`layerwatch.gcode.postprocess.insert_snapshots` put into the G-code
(``@layerwatch snapshot layer=<n> z=<z>``, ``M118 E1 layerwatch snapshot ...``
or the Klipper macro's ``layerwatch snapshot layer=<n> z=<z>`` response).
"""

from __future__ import annotations

import re
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

__all__ = ["PrinterStatus", "SnapshotTrigger", "Printer", "parse_trigger"]

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


@dataclass(frozen=True)
class PrinterStatus:
    """What the printer is doing.

    Attributes
    ----------
    state : str
        ``"idle"``, ``"printing"``, ``"paused"``, ``"cancelled"``, ``"finished"``,
        ``"error"`` or ``"offline"``.
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
    """

    layer: int
    z: float
    source: str = ""
    time: float = field(default_factory=time.monotonic)


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

    def close(self) -> None:
        """Release connections and threads (idempotent)."""
        return None

    def __enter__(self) -> Printer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
