"""Top-view and marker settings (config sections ``[topview]``, ``[markers]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from layerwatch.geometry.topview import TopView
from layerwatch.settings_base import Section

__all__ = ["TopViewSettings", "MarkerSettings"]


class TopViewSettings(Section):
    """Observed square and scale of the virtual top view (paper: 90 mm, 6.67 px/mm)."""

    px_per_mm: float = Field(6.67, gt=0, le=100)
    width_mm: float = Field(90.0, gt=0)
    height_mm: float = Field(90.0, gt=0)
    center_mm: tuple[float, float] = (0.0, 0.0)

    def topview(self):
        return TopView(self.px_per_mm, self.width_mm, self.height_mm, tuple(self.center_mm))


class MarkerSettings(Section):
    """Bed markers that give the camera pose; positions in bed mm (default: square corners)."""

    kind: Literal["dots", "aruco"] = "dots"
    positions_mm: list[tuple[float, float]] | None = None
    diameter_mm: float = Field(6.0, gt=0)
    aruco_dictionary: str = "DICT_4X4_50"
    # Where the camera stands, seen from the markers' centre: degrees counter-clockwise
    # from bed +X (-90 = in front of the printer). Only used to break the symmetry of a
    # symmetric dot layout (a square looks the same from four sides); ArUco ids need no cue.
    camera_azimuth_deg: float = -90.0
    max_pose_error_px: float = Field(3.0, gt=0)
