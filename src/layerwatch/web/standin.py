"""A virtual printer for the dashboard: the monitor's VirtualPrinter when present, else a tiny stand-in."""

from __future__ import annotations

import threading
from typing import Any

__all__ = ["StandInPrinter", "virtual_printer"]


class StandInPrinter:
    """Minimal object with the Printer method names (``status/pause/resume/cancel``)."""

    def __init__(self) -> None:
        self._state = "printing"
        self._lock = threading.Lock()
        self.calls: list[str] = []

    def status(self) -> dict[str, Any]:
        with self._lock:
            return {"state": self._state}

    def _set(self, name: str, state: str) -> None:
        with self._lock:
            self.calls.append(name)
            if self._state != "cancelled":
                self._state = state

    def pause(self) -> None:
        self._set("pause", "paused")

    def resume(self) -> None:
        self._set("resume", "printing")

    def cancel(self) -> None:
        self._set("cancel", "cancelled")


def virtual_printer() -> Any:
    """``layerwatch.monitor.printers.virtual.VirtualPrinter()`` if it exists, else :class:`StandInPrinter`."""
    try:
        from layerwatch.monitor.printers.virtual import VirtualPrinter
    except ImportError:
        return StandInPrinter()
    try:
        return VirtualPrinter()
    except TypeError:
        return StandInPrinter()
