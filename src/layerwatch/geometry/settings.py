"""Top-view and marker settings (config sections ``[topview]``, ``[markers]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.resolution import camera_px_per_mm
from layerwatch.geometry.topview import TopView
from layerwatch.settings_base import Section

__all__ = ["TopViewSettings", "MarkerSettings"]


class TopViewSettings(Section):
    """Observed square and scale of the virtual top view (paper: 90 mm, 6.67 px/mm).

    Attributes
    ----------
    px_per_mm : float
        Top-view pixels per bed mm (used as given with ``scale = "fixed"``).
    width_mm, height_mm : float
        Size of the observed square, mm.
    center_mm : (float, float)
        Its centre on the bed, mm.
    scale : {"fixed", "camera"}
        ``"camera"``: the top view samples the square at the camera's own
        resolution there (:func:`~layerwatch.geometry.resolution.camera_px_per_mm`,
        the median over the square), resolved by :meth:`for_camera` once the
        camera is known (the per-layer pipeline does it); ``"fixed"`` (default):
        ``px_per_mm``. ``docs/evaluation/resolution.md`` has the measurement.
    """

    px_per_mm: float = Field(6.67, gt=0, le=100)
    width_mm: float = Field(90.0, gt=0)
    height_mm: float = Field(90.0, gt=0)
    center_mm: tuple[float, float] = (0.0, 0.0)
    scale: Literal["fixed", "camera"] = "fixed"

    def topview(self):
        return TopView(self.px_per_mm, self.width_mm, self.height_mm, tuple(self.center_mm))

    def for_camera(self, camera: CameraModel) -> TopViewSettings:
        """These settings with a concrete scale for ``camera`` (``scale = "camera"`` resolved, else unchanged).

        The result has ``scale = "fixed"`` and ``px_per_mm`` the camera's
        median resolution over the observed square (rounded to 0.01 px/mm),
        so every user of the resolved settings gets the same top view.

        Raises
        ------
        CalibrationError
            ``scale = "camera"`` with a camera without a bed pose.
        """
        if self.scale != "camera":
            return self
        px = camera_px_per_mm(camera, self.center_mm, self.width_mm, self.height_mm)
        return self.model_copy(update={"px_per_mm": round(min(max(px, 0.5), 100.0), 2), "scale": "fixed"})


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
