"""Simulator settings (appearance, imperfections, camera effects)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from layerwatch.settings_base import Section

__all__ = ["SimSettings"]


class SimSettings(Section):
    """How virtual layer photos are made; defaults give a plausible webcam photo."""

    grid_px_per_mm: float = Field(8.0, gt=0, le=40, description="height-field resolution")
    grid_margin_mm: float = Field(10.0, ge=0, description="height field beyond the observed square")
    filament_rgb: tuple[float, float, float] = (0.85, 0.50, 0.16)
    bed_rgb: tuple[float, float, float] = (0.08, 0.075, 0.07)
    background_rgb: tuple[float, float, float] = (0.05, 0.05, 0.06)
    bed_size_mm: float | None = Field(None, description="bed square side; None = 2.4 x observed")
    marker_diameter_mm: float = Field(6.0, gt=0)
    markers_mm: list[tuple[float, float]] | None = None
    light_offset_mm: tuple[float, float, float] = (70.0, 0.0, 60.0)
    light_jitter_mm: float = Field(15.0, ge=0)
    light_intensity: float = Field(0.9, gt=0)
    light_intensity_jitter: float = Field(0.08, ge=0)
    ambient: float = Field(0.16, ge=0)
    fill: float = Field(0.22, ge=0)
    exposure: float = Field(1.0, gt=0)
    exposure_drift: float = Field(0.06, ge=0)
    colour_drift: float = Field(0.03, ge=0)
    white_balance: tuple[float, float, float] = Field((1.0, 1.0, 1.0), description="fixed per-channel gain (BGR)")
    vignetting: float = Field(0.3, ge=0, le=1)
    blur_px: tuple[float, float] = (0.5, 1.1)
    read_noise: float = Field(0.012, ge=0)
    shot_noise: float = Field(0.02, ge=0)
    width_jitter: float = Field(0.06, ge=0, description="relative bead-width sd per bead")
    extrusion_noise: float = Field(0.10, ge=0, description="bead-width wobble amplitude")
    position_jitter_mm: float = Field(0.02, ge=0)
    z_jitter_mm: float = Field(0.01, ge=0)
    renderer: Literal["raster", "blender"] = Field(
        "raster", description="raster: the simulator's own ray caster; blender: Blender Cycles (photoreal, seconds a photo)")
    blender_samples: int = Field(32, ge=1, le=4096, description="Cycles samples per pixel (photoreal)")
    blender_threads: int = Field(0, ge=0, le=256, description="Cycles threads (0 = all cores)")
    blender_timeout_s: float = Field(900.0, gt=0, le=86_400, description="longest wait for one photoreal photo")
