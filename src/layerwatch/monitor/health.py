"""Printer and camera faults of a running monitor: when they start, how long they last, when to tell.

A host that does not answer (or answers nonsense) and a camera that raises or
sends unusable frames are *faults*, never print failures: the monitor keeps
running, retries, and resumes watching when they end. :class:`FaultTracker`
keeps one fault's episode (start, attempts, last error) and says when it is
time to notify: after a grace period (a host) or after a number of bad frames
in a row (a camera), once per episode.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

from layerwatch.pipeline.watch_settings import FaultSettings

__all__ = ["FaultSettings", "Fault", "FaultTracker"]


@dataclass
class Fault:
    """One ongoing fault episode.

    Attributes
    ----------
    source : str
        ``"printer"`` or ``"camera"``.
    since : float
        Wall-clock start, s since the epoch (for records).
    started : float
        Monotonic start, s.
    count : int
        Failed attempts (polls, frames) so far.
    error : str
        The last error, one line.
    notified : bool
        A notification went out for this episode.
    """

    source: str
    since: float
    started: float
    count: int = 0
    error: str = ""
    notified: bool = False

    def to_dict(self, now: float) -> dict:
        """JSON-able view with the episode's duration so far (``now``: monotonic, s)."""
        out = asdict(self)
        out["duration_s"] = round(now - self.started, 3)
        return out


class FaultTracker:
    """Episodes of one fault source.

    Parameters
    ----------
    source : str
        ``"printer"`` or ``"camera"``.
    grace_s : float, optional
        Notify once the episode lasted this long, s.
    after_n : int, optional
        Notify once the episode counts this many failures.
    clock : callable
        Monotonic time, s.
    """

    def __init__(self, source: str, *, grace_s: float | None = None, after_n: int | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.source, self.grace_s, self.after_n, self._clock = source, grace_s, after_n, clock
        self.current: Fault | None = None
        self.episodes = 0

    def failed(self, error: str) -> tuple[bool, bool]:
        """Count one failure.

        Returns
        -------
        started : bool
            This failure opened a new episode.
        notify : bool
            The episode just became worth a notification (at most once per episode).
        """
        now = self._clock()
        f = self.current
        started = f is None
        if f is None:
            f = self.current = Fault(self.source, time.time(), now)
            self.episodes += 1
        f.count += 1
        f.error = error
        due = ((self.grace_s is not None and now - f.started >= self.grace_s)
               or (self.after_n is not None and f.count >= self.after_n))
        notify = due and not f.notified
        f.notified = f.notified or notify
        return started, notify

    def recovered(self) -> Fault | None:
        """End the episode (if any) and return it."""
        f, self.current = self.current, None
        return f

    def state(self) -> dict | None:
        """The ongoing episode as a dict (see :meth:`Fault.to_dict`), or None."""
        return None if self.current is None else self.current.to_dict(self._clock())
