"""Reference-rendering settings (config section ``[render]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from layerwatch.settings_base import Section

__all__ = ["RenderSettings"]


class RenderSettings(Section):
    """How the reference of a layer is rendered."""

    backend: Literal["fast", "blender"] = "fast"
    material_rgb: tuple[float, float, float] = (0.85, 0.85, 0.82)
    bed_rgb: tuple[float, float, float] = (0.12, 0.12, 0.13)
    light: Literal["ring", "directional"] = "ring"
    light_azimuth_deg: float = 225.0
    light_elevation_deg: float = 45.0
    layers_visible_below: int = Field(3, ge=0)
