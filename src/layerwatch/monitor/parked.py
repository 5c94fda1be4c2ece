"""Reject frames taken while the head was not at its park spot.

The snapshot block parks the head out of the camera's view before the trigger
(:mod:`layerwatch.gcode.postprocess`). Where it parks is read from the job's
own G-code: the machine model of the G-code reader
(:func:`layerwatch.gcode.reader.run`) gives the commanded XY at each trigger
line, in G-code coordinates, whatever park rule the file was prepared with.
When a trigger arrives, :class:`ParkedCamera` grabs the frame, then asks the
printer where the head is (Moonraker: ``gcode_move.gcode_position``; OctoPrint:
the firmware's ``M114`` reply, :class:`M114Position`). The block waits for the
park move to finish (``M400``) before its trigger, and each layer parks at its
own height, so a head still at this layer's park spot after the frame was there
while it was taken. When the position is more than ``tolerance_mm`` (XY) or
``z_tolerance_mm`` (Z) from the spot, the frame is rejected with a
:class:`FrameNotParked` error whose message the monitor records as that
layer's result (never as a pause).

Both hosts report the *commanded* position (Klipper's ``gcode_position``, Marlin's
``M114``), which runs ahead of the head once the next move is read. That errs on the
safe side: the trigger follows an ``M400`` at the park spot, so a commanded position
still there means the head is there, and one already elsewhere rejects the frame as
the head starts to leave.

Asking *after* the grab matters on OctoPrint: it queues ``M114`` behind the
line being executed, so the reply comes when the dwell at the park spot ends
(and before the move back, which OctoPrint sends only after that reply's
``ok``); asking before would delay the photo to the end of the dwell. A printer
that does not answer leaves the frame unchecked (logged;
:attr:`ParkedCamera.verdicts` says ``"unknown"``).
"""

from __future__ import annotations

import logging
import math
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from layerwatch.errors import CameraError, ConfigError, LayerwatchError
from layerwatch.gcode.reader import run
from layerwatch.monitor.jobs import find_triggers

__all__ = ["FrameNotParked", "ParkCheck", "ParkedCamera", "M114Position", "park_spots"]

log = logging.getLogger("layerwatch.monitor.parked")

Position = tuple[float, float, float]


class FrameNotParked(CameraError):
    """The head was not at the park spot while the frame was taken."""


def park_spots(data: bytes) -> dict[int, Position]:
    """Where the head stands at each layer's snapshot trigger.

    Parameters
    ----------
    data : bytes
        The prepared G-code (ASCII).

    Returns
    -------
    dict of int to (float, float, float)
        Layer index -> commanded (X, Y, Z) at its first trigger line, G-code coordinates, mm.
        Layers whose position is not known (no move before the trigger) are left out.
    """
    found = find_triggers(data)
    if not found:
        return {}
    first: dict[int, int] = {}
    for line, layer, _ in found:
        first.setdefault(layer, line)
    layers = sorted(first, key=lambda k: first[k])
    probe = run(data, np.array([first[k] for k in layers], np.int64))[5]
    return {k: (float(row[0]), float(row[1]), float(row[2])) for k, row in zip(layers, probe, strict=True)
            if np.isfinite(row[:3]).all()}


@dataclass
class ParkCheck:
    """Compare a reported head position with the layer's park spot.

    Attributes
    ----------
    spots : dict of int to (float, float, float)
        Park XYZ per layer (:func:`park_spots`), mm.
    tolerance_mm : float
        Largest XY distance from the park spot still counted as parked, mm.
    z_tolerance_mm : float
        Largest Z difference, mm. The park spot is usually the same XY for every layer, but
        its Z (layer top + lift) is not: a stale trigger of an earlier layer, seen while the
        head is parked for a later one, is told apart by Z. Keep it below the layer height.
    """

    spots: dict[int, Position]
    tolerance_mm: float = 1.0
    z_tolerance_mm: float = 0.05

    def __post_init__(self) -> None:
        for name, v in (("--park-tolerance", self.tolerance_mm), ("Z tolerance", self.z_tolerance_mm)):
            if not (math.isfinite(v) and 0 < v < 1000):
                raise ConfigError(f"{name} {v}: give a distance in mm above 0 (e.g. 1).")

    def reason(self, layer: int, position: Position) -> str | None:
        """Why a frame of ``layer`` taken at ``position`` (X, Y, Z, mm) is rejected, or ``None`` when parked.

        A layer without a known park spot is not checked (``None``).
        """
        spot = self.spots.get(layer)
        if spot is None:
            return None
        d = math.hypot(position[0] - spot[0], position[1] - spot[1])
        dz = abs(position[2] - spot[2])
        if d <= self.tolerance_mm and dz <= self.z_tolerance_mm:
            return None
        return (f"frame rejected: the head was at X{position[0]:.2f} Y{position[1]:.2f} Z{position[2]:.2f}, not at "
                f"layer {layer}'s park spot X{spot[0]:.2f} Y{spot[1]:.2f} Z{spot[2]:.2f} (off by {d:.2f} mm in XY, "
                f"{dz:.2f} mm in Z; tolerance {self.tolerance_mm:g} / {self.z_tolerance_mm:g} mm) when the photo was "
                "taken: the printer did not hold at the park spot for the photo (a late trigger, or a block "
                "without a dwell after the trigger: prepare the file again with `layerwatch gcode prepare`)")


class ParkedCamera:
    """A camera whose frames are only accepted while the printer reports the head parked.

    Parameters
    ----------
    camera : Camera
        Frame source (``grab()``; ``set_layer`` is passed on when it has one).
    check : ParkCheck
        Park spots and tolerance.
    position : callable
        ``position() -> (x, y, z)`` or ``None`` (the host cannot tell); may raise
        :class:`~layerwatch.errors.PrinterError`.
    """

    def __init__(self, camera: Any, check: ParkCheck, position: Callable[[], Position | None]) -> None:
        self.camera, self.check, self.position = camera, check, position
        self.layer = 0
        #: per layer, how the frame was checked: ``"parked"``, ``"unknown"`` or the rejection reason
        self.verdicts: dict[int, str] = {}

    def __getattr__(self, name: str) -> Any:
        return getattr(self.camera, name)

    def set_layer(self, layer: int) -> None:
        """Remember the layer of the next frame (and tell the wrapped camera)."""
        self.layer = int(layer)
        if hasattr(self.camera, "set_layer"):
            self.camera.set_layer(layer)

    def _where(self) -> Position | None:
        try:
            return self.position()
        except LayerwatchError as exc:
            log.warning("head position unknown for layer %d: %s", self.layer, exc)
            return None

    def grab(self) -> np.ndarray:
        """The frame, if the head is still at the layer's park spot after it was taken.

        Raises
        ------
        FrameNotParked
            A reported position is off the park spot (the message says where, and what to do).
        CameraError
            From the wrapped camera.
        """
        return self._parked(self.camera.grab())

    def grab_encoded(self) -> Any:
        """:meth:`grab` of the wrapped camera's :meth:`~layerwatch.monitor.cameras.Camera.grab_encoded` (the frame
        as the camera sent it; only when the camera is ``encoded``)."""
        return self._parked(self.camera.grab_encoded())

    def _parked(self, frame: Any) -> Any:
        """``frame`` if the head is still at the layer's park spot (see :meth:`grab`)."""
        pos = self._where()
        why = None if pos is None else self.check.reason(self.layer, pos)
        if why is not None:
            self.verdicts[self.layer] = why
            raise FrameNotParked(why)
        self.verdicts[self.layer] = "unknown" if pos is None else "parked"
        return frame


#: the position in a Marlin/RepRapFirmware/Klipper ``M114`` reply (``X:1.00 Y:2.00 Z:3.00 E:0.00 Count ...``)
_M114 = re.compile(r"X:\s*(-?[0-9.]+)\s+Y:\s*(-?[0-9.]+)\s+Z:\s*(-?[0-9.]+)")


class M114Position:
    """The head position through OctoPrint: send ``M114``, read the reply from its terminal log.

    OctoPrint has no position API; its websocket pushes the serial log (``Recv: ...`` lines in
    ``current.logs``), where the firmware's ``M114`` reply appears.

    Parameters
    ----------
    printer : OctoPrintPrinter
        Connector with the websocket open (``listeners`` receive its messages).
    timeout_s : float
        How long to wait for the reply: longer than the dwell at the park spot plus OctoPrint's
        log push interval (0.5 s), s.
    """

    def __init__(self, printer: Any, timeout_s: float = 5.0) -> None:
        self.printer, self.timeout_s = printer, float(timeout_s)
        self._lock = threading.Lock()
        self._reply = threading.Event()
        self._waiting = False
        self._sent = False  # our M114 was seen going out (its ``Send:`` line)
        self._value: Position | None = None
        printer.listeners.append(self._on_message)

    def _on_message(self, msg: dict) -> None:
        body = msg.get("current")
        if not self._waiting or not isinstance(body, dict) or not isinstance(body.get("logs"), list):
            return
        for line in body["logs"]:
            if not isinstance(line, str):
                continue
            if line.startswith("Send:") and "M114" in line:  # our request went out: the reply follows it
                self._sent = True
                continue
            # a position line before our M114 is an older reply (OctoPrint's own M114 on a cancel or pause,
            # an earlier job's): it was read as this frame's and rejected a parked frame
            m = _M114.search(line) if self._sent and line.startswith("Recv:") else None
            if m is not None:
                with self._lock:
                    if self._waiting:
                        self._value = (float(m[1]), float(m[2]), float(m[3]))
                        self._waiting = False
                        self._reply.set()
                return

    def __call__(self) -> Position | None:
        """Ask the firmware (``M114``) and wait for the reply; ``None`` when none comes in time.

        Raises
        ------
        PrinterError
            OctoPrint refused the command (not connected, unreachable).
        """
        with self._lock:
            self._reply.clear()
            self._value, self._waiting, self._sent = None, True, False
        self.printer.send_gcode("M114")
        if not self._reply.wait(self.timeout_s):
            with self._lock:
                self._waiting = False
            log.warning("no M114 reply within %.1f s; the frame is not checked", self.timeout_s)
        return self._value
