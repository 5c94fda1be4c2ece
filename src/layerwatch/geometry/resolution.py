"""The camera's real resolution on the bed: image pixels per bed millimetre.

The top view samples the observed square at ``px_per_mm`` (the paper's 6.67
px/mm). What the camera resolves there depends on its sensor, lens, distance
and tilt: one image pixel covers a patch of bed whose size varies over the
square (closer rows are finer, the tilt foreshortens the rows). This module
measures it from the calibrated model, lens distortion included: the camera
projects bed points of the plane ``Z = z`` (:func:`cv2.projectPoints`) and the
local scale at a point is ``sqrt(|det J|)`` of the Jacobian ``J`` (image px
per bed mm, 2 x 2, central differences of 0.5 mm): the side of the square of
bed that one image pixel covers, inverted (an area-preserving mean of the two
axes).

:func:`camera_px_per_mm` summarises it over the observed square (the median
over a 9 x 9 grid, or the value at the square's centre). ``[topview] scale =
"camera"`` (:class:`~layerwatch.geometry.settings.TopViewSettings`) uses the
median as the top view's ``px_per_mm``: the top view then holds what the
camera resolves, no more (interpolated pixels) and no less (detail averaged
away). ``docs/evaluation/resolution.md`` measures whether it helps.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.errors import CalibrationError
from layerwatch.geometry.camera import CameraModel

__all__ = ["camera_px_per_mm", "local_px_per_mm"]

#: half-step of the central differences, bed mm
_STEP_MM = 0.5


def local_px_per_mm(camera: CameraModel, points_mm: np.ndarray, z: float = 0.0) -> np.ndarray:
    """Image pixels per bed millimetre at bed points of the plane ``Z = z``.

    Parameters
    ----------
    camera : CameraModel
        Calibrated camera with a bed pose (its ``image_size`` is the photo size).
    points_mm : ndarray, shape (N, 2)
        Bed points, mm.
    z : float
        Height of the plane, mm.

    Returns
    -------
    ndarray, shape (N,), float64
        ``sqrt(|det J|)`` of the projection's Jacobian (px/mm); 0 where a
        point is behind the camera.

    Raises
    ------
    CalibrationError
        The camera has no pose.
    """
    if not camera.has_pose:
        raise CalibrationError("the camera has no bed pose; run `layerwatch calibrate --markers PHOTO` first.")
    p = np.asarray(points_mm, np.float64).reshape(-1, 2)
    d = _STEP_MM
    offsets = np.array([[d, 0], [-d, 0], [0, d], [0, -d]])
    pts = (p[:, None, :] + offsets[None]).reshape(-1, 2)
    pts3 = np.c_[pts, np.full(len(pts), float(z))]
    rvec, tvec = camera.pose
    uv = cv2.projectPoints(pts3, rvec, tvec, camera.K, camera.dist)[0].reshape(-1, 4, 2)
    jx = (uv[:, 0] - uv[:, 1]) / (2 * d)  # d(u, v) / dx
    jy = (uv[:, 2] - uv[:, 3]) / (2 * d)  # d(u, v) / dy
    det = np.abs(jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0])
    depth = (pts3 @ camera.R.T + np.asarray(tvec, np.float64).reshape(1, 3))[:, 2].reshape(-1, 4)
    return np.where((depth > 0).all(axis=1), np.sqrt(det), 0.0)


def camera_px_per_mm(camera: CameraModel, center_mm: tuple[float, float], width_mm: float, height_mm: float,
                     *, where: str = "median", z: float = 0.0) -> float:
    """The camera's resolution over the observed square, image px per bed mm.

    Parameters
    ----------
    camera : CameraModel
    center_mm, width_mm, height_mm
        The observed square on the bed (``[topview]``).
    where : {"median", "center"}
        Median over a 9 x 9 grid of the square, or the value at its centre.
    z : float
        Plane height, mm (the bed: 0).

    Returns
    -------
    float
        px/mm, > 0.

    Raises
    ------
    CalibrationError
        No pose, or the square is not in front of the camera.
    """
    cx, cy = (float(v) for v in center_mm)
    if where == "center":
        pts = np.array([[cx, cy]])
    elif where == "median":
        gx, gy = np.meshgrid(np.linspace(-0.5, 0.5, 9) * width_mm + cx, np.linspace(-0.5, 0.5, 9) * height_mm + cy)
        pts = np.c_[gx.ravel(), gy.ravel()]
    else:
        raise ValueError(f"where must be 'median' or 'center', got {where!r}")
    s = local_px_per_mm(camera, pts, z)
    s = s[s > 0]
    if s.size == 0:
        raise CalibrationError("the observed square is behind the camera; check the camera pose and [topview].")
    return float(np.median(s))
