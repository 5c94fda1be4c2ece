"""A virtual printer that prints one layer every ``layer_seconds`` (a farm without hardware)."""

from __future__ import annotations

from pathlib import Path

from layerwatch.monitor.printers.virtual import VirtualPrinter

__all__ = ["PacedVirtualPrinter"]


class PacedVirtualPrinter(VirtualPrinter):
    """:class:`~layerwatch.monitor.printers.virtual.VirtualPrinter` replaying one layer per ``layer_seconds``.

    :meth:`start` replays in a background thread: it runs the G-code up to the
    next snapshot trigger, then waits ``layer_seconds``; pause holds it, resume
    and cancel act at once. The monitor then watches it as it watches a real
    host (polling triggers and state).

    Parameters
    ----------
    gcode : bytes, str or Path
        G-code with layerwatch snapshot triggers.
    layer_seconds : float
        Time per layer, s (> 0).
    name : str
        File name reported in the status.
    """

    def __init__(self, gcode: bytes | str | Path, layer_seconds: float, *, name: str = "virtual.gcode") -> None:
        super().__init__(gcode, name=name)
        self.layer_seconds = float(layer_seconds)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._resumed.wait()
            if self._stop.is_set() or self._state in ("cancelled", "finished"):
                return
            if self._state != "printing":
                continue
            if self.step_to_next_trigger() is None and self._state == "finished":
                return
            self._stop.wait(self.layer_seconds)
