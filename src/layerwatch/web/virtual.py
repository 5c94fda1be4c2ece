"""The dashboard's virtual printer: the monitor's :class:`VirtualPrinter` on a bundled G-code."""

from __future__ import annotations

from pathlib import Path

from layerwatch.examples import PART_GCODE
from layerwatch.monitor.printers.virtual import VirtualPrinter

__all__ = ["virtual_printer"]


def virtual_printer(gcode: bytes | str | Path | None = None) -> VirtualPrinter:
    """A :class:`~layerwatch.monitor.printers.virtual.VirtualPrinter` for trying the dashboard's buttons.

    Parameters
    ----------
    gcode : bytes, str or Path, optional
        G-code text or file; default: the bundled example ``layerwatch/examples/part.gcode``.

    Returns
    -------
    VirtualPrinter
        In state ``"printing"``, not replaying (``pause/resume/cancel`` change its state,
        ``start()`` replays the file in a thread).

    Raises
    ------
    PrinterError
        The G-code file cannot be read.
    """
    if gcode is None:
        gcode = PART_GCODE
    return VirtualPrinter(gcode)
