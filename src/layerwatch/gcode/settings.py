"""Printer profile and snapshot-block settings (config sections ``[printer]``, ``[snapshot]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from layerwatch.settings_base import Section

__all__ = ["PrinterProfile", "SnapshotSettings"]


class PrinterProfile(Section):
    """The printer's build volume and filament, in bed mm."""

    volume_min_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    volume_max_mm: tuple[float, float, float] = (250.0, 210.0, 210.0)
    filament_diameter_mm: float = Field(1.75, gt=0, le=5)
    firmware: Literal["marlin", "klipper", "reprap", "generic"] = "marlin"


class SnapshotSettings(Section):
    """The block inserted after each layer (paper Table 1)."""

    profile: Literal["paper", "octoprint", "klipper", "timelapse", "m240"] = "octoprint"
    every_n_layers: int = Field(1, ge=1)
    retract_mm: float = Field(1.0, ge=0, le=20)
    lift_mm: float = Field(5.0, ge=0, le=100)
    park_xy_mm: tuple[float, float] | None = None
    travel_feed_mm_min: float = Field(9000.0, gt=0)
    settle_ms: int = Field(500, ge=0, le=60000)
    retract_feed_mm_min: float = Field(2400.0, gt=0)
    light_tool: int = Field(1, ge=0, le=15)
    indicator_pin: int = Field(4, ge=0, le=255)
