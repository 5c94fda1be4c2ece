"""Printer profile and snapshot-block settings (config sections ``[printer]``, ``[snapshot]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from layerwatch.settings_base import Section

__all__ = ["PrinterProfile", "SnapshotSettings"]


class PrinterProfile(Section):
    """The printer's build volume and filament, in bed mm.

    The volume is the bed of last resort for ``gcode prepare``: the bed the
    file states (``bed_shape``, ``printable_area`` ...) or ``--bed`` comes first.
    """

    volume_min_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    volume_max_mm: tuple[float, float, float] = (250.0, 210.0, 210.0)
    filament_diameter_mm: float = Field(1.75, gt=0, le=5, allow_inf_nan=False)
    firmware: Literal["marlin", "klipper", "reprap", "generic"] = "marlin"

    @field_validator("volume_min_mm", "volume_max_mm")
    @classmethod
    def _volume_finite(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(abs(x) < 1e4 for x in v):  # also refuses NaN and infinity
            raise ValueError("every coordinate must be a finite number of mm below 10000")
        return v


class SnapshotSettings(Section):
    """The block inserted after each layer (paper Table 1); see :mod:`layerwatch.gcode.snapshot`.

    ``retract_mm`` is the retraction held during the photo: the slicer's own
    retraction at the layer change counts towards it, and when the file states
    its ``retract_length`` (and ``retract_mm`` was not set explicitly) that
    length is used. ``settle_ms`` is the dwell at the park spot after the
    trigger (the photo's window); the ``klipper`` profile instead holds until
    the host confirms the frame, at most ``hold_s``. ``light_tool`` and
    ``indicator_pin`` (paper profile) are only emitted when set.
    """

    profile: Literal["paper", "octoprint", "klipper", "timelapse", "m240"] = "octoprint"
    every_n_layers: int = Field(1, ge=1, le=100000)
    retract_mm: float = Field(1.0, ge=0, le=20, allow_inf_nan=False)
    lift_mm: float = Field(5.0, ge=0, le=100, allow_inf_nan=False)
    park_xy_mm: tuple[float, float] | None = None
    travel_feed_mm_min: float = Field(9000.0, gt=0, le=60000, allow_inf_nan=False)
    z_feed_mm_min: float = Field(600.0, gt=0, le=60000, allow_inf_nan=False)
    settle_ms: int = Field(1000, ge=100, le=60000)
    hold_s: float = Field(10.0, gt=0, le=120, allow_inf_nan=False)
    retract_feed_mm_min: float = Field(2400.0, gt=0, le=60000, allow_inf_nan=False)
    light_tool: int | None = Field(None, ge=0, le=15)
    indicator_pin: int | None = Field(None, ge=0, le=255)

    @field_validator("park_xy_mm")
    @classmethod
    def _park_finite(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not all(abs(x) < 1e4 for x in v):  # also refuses NaN and infinity
            raise ValueError("park X and Y must be finite numbers of mm")
        return v
