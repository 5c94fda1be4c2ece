"""Reject frames taken while the head was not at its park spot.

The snapshot block parks the head out of the camera's view before the trigger
(:mod:`layerwatch.gcode.postprocess`). Where it parks is read from the job's
own G-code: the machine model of the G-code reader
(:func:`layerwatch.gcode.reader.run`) gives the commanded XY at each trigger
line, in G-code coordinates, whatever park rule the file was prepared with.
When a trigger arrives, :class:`ParkedCamera` asks the printer where the head
is (Moonraker: ``gcode_move.gcode_position``) right before and right after it
grabs the frame; when either position is more than ``tolerance_mm`` from the
park spot, the frame is rejected with a :class:`FrameNotParked` error whose
message the monitor records as that layer's result (and never as a pause).

A host that cannot report the position (OctoPrint has no position API) leaves
the frame unchecked (logged; :attr:`ParkedCamera.verdicts` says ``"unknown"``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from layerwatch.errors import CameraError, ConfigError, LayerwatchError
from layerwatch.gcode.reader import run
from layerwatch.monitor.jobs import find_triggers

__all__ = ["FrameNotParked", "ParkCheck", "ParkedCamera", "park_spots"]

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
    layers = sorted(first, key=first.get)
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
        """The frame, if the head was parked before and after it was taken.

        Raises
        ------
        FrameNotParked
            A reported position is off the park spot (the message says where, and what to do).
        CameraError
            From the wrapped camera.
        """
        before = self._where()
        frame = self.camera.grab()
        after = self._where()
        for pos in (before, after):
            why = None if pos is None else self.check.reason(self.layer, pos)
            if why is not None:
                self.verdicts[self.layer] = why
                raise FrameNotParked(why)
        self.verdicts[self.layer] = "parked" if before is not None and after is not None else "unknown"
        return frame
