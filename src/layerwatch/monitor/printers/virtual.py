"""A virtual printer that replays a G-code file and emits snapshot triggers.

Used by the demo and tests: ``step_to_next_trigger()`` advances
deterministically; ``start()`` replays in a background thread.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from layerwatch.errors import PrinterError
from layerwatch.monitor.printers.base import Printer, PrinterStatus, SnapshotTrigger, parse_line

if TYPE_CHECKING:
    from layerwatch.gcode.objects import PrintObject

__all__ = ["VirtualPrinter"]

_Z = re.compile(r"^\s*G[01]\b[^;]*?\bZ(?P<z>[-+0-9.]+)", re.IGNORECASE)


class VirtualPrinter(Printer):
    """Replay G-code line by line.

    Parameters
    ----------
    gcode : bytes, str or Path
        G-code text (bytes) or a file path.
    name : str
        File name reported in :class:`PrinterStatus`.
    on_trigger : callable, optional
        Called as ``on_trigger(trigger)`` (e.g. to render the camera frame).
    line_delay_s : float
        Delay per line when replaying in a thread (0 = as fast as possible).
    """

    name = "virtual"

    def __init__(
        self,
        gcode: bytes | str | Path,
        *,
        name: str = "virtual.gcode",
        on_trigger: Callable[[SnapshotTrigger], None] | None = None,
        line_delay_s: float = 0.0,
    ) -> None:
        super().__init__()
        if isinstance(gcode, (str, Path)):
            path = Path(gcode)
            try:
                gcode = path.read_bytes()
            except OSError as exc:
                raise PrinterError(f"cannot read G-code {path}: {exc.strerror}; check the path.") from exc
            name = path.name
        self._lines = gcode.decode("utf-8", errors="replace").splitlines()
        self._file = name
        self._pos = 0
        self._state = "printing"
        self._layer: int | None = None
        self._z: float | None = None
        self._sent: list[str] = []
        self._delay = float(line_delay_s)
        self._resumed = threading.Event()
        self._resumed.set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.pause_count = 0
        #: names of the objects cancelled through :meth:`cancel_object`
        self.cancelled_objects: list[str] = []
        if on_trigger is not None:
            self.subscribe(on_trigger)

    # -- replay ---------------------------------------------------------
    def _exec(self, line: str) -> SnapshotTrigger | None:
        m = _Z.match(line)
        if m:
            try:
                self._z = float(m["z"])
            except ValueError:
                pass
        trig = parse_line(line, source=self.name)
        if trig is not None and not trig.signal and trig.layer == self._layer:
            return None  # second trigger line of the same block (@ command + M118 echo)
        return trig

    @property
    def needs_stepping(self) -> bool:
        """True until :meth:`start` runs the replay in its own thread."""
        return self._thread is None

    def step_to_next_trigger(self) -> SnapshotTrigger | None:
        """Execute lines up to and including the next trigger.

        Returns
        -------
        SnapshotTrigger or None
            The trigger, or ``None`` when the file ended (state ``finished``)
            or the job is paused/cancelled.
        """
        if self._state != "printing":
            return None
        while self._pos < len(self._lines):
            line = self._lines[self._pos]
            self._pos += 1
            trig = self._exec(line)
            if trig is not None:
                if not trig.signal:
                    self._layer = trig.layer
                self._emit(trig)
                return trig
        self._state = "finished"
        return None

    def start(self) -> None:
        """Replay the rest of the file in a background thread (honours pause)."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="virtual-printer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._resumed.wait()
            if self._stop.is_set() or self._state in ("cancelled", "finished"):
                return
            if self._state != "printing":
                continue
            if self._pos >= len(self._lines):
                self._state = "finished"
                return
            line = self._lines[self._pos]
            self._pos += 1
            trig = self._exec(line)
            if trig is not None:
                self._layer = trig.layer
                self._emit(trig)
            if self._delay:
                self._stop.wait(self._delay)

    def join(self, timeout: float | None = None) -> None:
        """Wait for the background replay to end."""
        if self._thread is not None:
            self._thread.join(timeout)

    # -- Printer interface ------------------------------------------------
    def status(self) -> PrinterStatus:
        n = max(len(self._lines), 1)
        return PrinterStatus(self._state, self._file, self._layer, self._z, min(self._pos / n, 1.0))

    def pause(self) -> None:
        if self._state == "printing":
            self._state = "paused"
            self.pause_count += 1
            self._resumed.clear()

    def resume(self) -> None:
        if self._state == "paused":
            self._state = "printing"
            self._resumed.set()

    def cancel(self) -> None:
        if self._state in ("printing", "paused"):
            self._state = "cancelled"
            self._resumed.set()

    def send_gcode(self, lines: str | Iterable[str]) -> None:
        self._sent.extend([lines] if isinstance(lines, str) else list(lines))

    def cancel_object(self, obj: PrintObject) -> None:
        """Record the firmware's line: ``EXCLUDE_OBJECT NAME=..`` (Klipper labels) or ``M486 P<id>``."""
        if obj.klipper_name is None and obj.firmware_id is None:
            raise PrinterError(f"the job has no firmware labels, so the printer cannot skip {obj.name}.")
        self.send_gcode(f"EXCLUDE_OBJECT NAME={obj.klipper_name}" if obj.klipper_name else f"M486 P{obj.firmware_id}")
        self.cancelled_objects.append(obj.name)

    def show_message(self, text: str) -> None:
        self.send_gcode(f"M117 {text}")

    @property
    def sent(self) -> list[str]:
        """G-code lines sent through :meth:`send_gcode`."""
        return list(self._sent)

    def close(self) -> None:
        self._stop.set()
        self._resumed.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2.0)
