"""Monitoring settings (config sections ``[policy]`` and ``[notify]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from layerwatch.settings_base import Section

__all__ = ["PolicySettings", "NotifySettings"]


class PolicySettings(Section):
    """When a failure pauses the print (defaults come from the evaluation report)."""

    pause_ratio: float = Field(0.10, ge=0, le=1)
    # the ratio rule also needs this much anomalous area (mm^2): on a small
    # footprint two or three blocks of 1.44 mm^2 exceed any useful pause ratio
    min_area_mm2: float = Field(5.0, ge=0)
    consecutive_layers: int = Field(2, ge=1)
    strong_outside_area_mm2: float = Field(150.0, ge=0)
    growth_ratio: float = Field(1.5, ge=1)
    action: Literal["notify", "pause", "cancel"] = "pause"
    wait_for_verdict: bool = False
    skip_first_layers: int = Field(1, ge=0)
    growth_min_area_mm2: float = Field(25.0, ge=0)
    strong_action: Literal["notify", "pause", "cancel"] = "pause"
    notify_single_layer: bool = True


class NotifySettings(Section):
    """Where alerts go (Apprise URLs and/or a JSON webhook), rate-limited."""

    apprise_urls: list[str] = Field(default_factory=list)
    webhook_url: str | None = None
    min_interval_s: float = Field(60.0, ge=0)
