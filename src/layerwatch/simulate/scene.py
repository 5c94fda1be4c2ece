"""A virtual camera looking at the observed square, and default bed markers."""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView

__all__ = ["default_camera", "default_markers", "look_at"]


def default_markers(topview: TopView) -> np.ndarray:
    """Marker centres, bed mm, shape (4, 2): the observed square's corners."""
    return topview.corners_mm.copy()


def look_at(eye: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rvec, tvec)`` of ``camera_from_bed`` for a camera at ``eye`` looking at ``target``.

    Image x points along ``forward x (0, 0, 1)`` (bed-horizontal), image y down.
    """
    f = np.asarray(target, float) - np.asarray(eye, float)
    f /= np.linalg.norm(f)
    x = np.cross(f, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-9:  # looking straight down
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    R = np.stack([x, y, f])
    t = -R @ np.asarray(eye, float)
    return cv2.Rodrigues(R)[0].reshape(3), t


def default_camera(
    topview: TopView,
    image_size: tuple[int, int] = (1280, 720),
    elevation_deg: float = 45.0,
    azimuth_deg: float = -90.0,
    distance_mm: float | None = None,
    hfov_deg: float = 70.0,
    dist: tuple[float, ...] = (-0.06, 0.012, 0.0, 0.0, 0.0),
    fill: float = 0.78,
) -> CameraModel:
    """A webcam on a tripod looking at the centre of the observed square.

    Parameters
    ----------
    topview : TopView
        Its ``center_mm`` is the target; its corners must be in view.
    image_size : (int, int)
        ``(width, height)`` px.
    elevation_deg : float
        Angle of the line of sight above the bed plane, degrees.
    azimuth_deg : float
        Direction from the target to the camera, degrees counter-clockwise
        from bed +X (-90 = in front of the printer, looking towards +Y).
    distance_mm : float or None
        Camera-target distance; None chooses the distance at which the
        observed square's corners span ``fill`` of the image.
    hfov_deg : float
        Horizontal field of view, degrees.
    dist : tuple of float
        OpenCV distortion ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    CameraModel
        With ``K``, ``dist``, pose and ``markers_mm`` = :func:`default_markers`.
    """
    w, h = (int(v) for v in image_size)
    f = (w / 2.0) / np.tan(np.deg2rad(hfov_deg) / 2.0)
    K = np.array([[f, 0, (w - 1) / 2.0], [0, f, (h - 1) / 2.0], [0, 0, 1.0]])
    el, az = np.deg2rad(elevation_deg), np.deg2rad(azimuth_deg)
    target = np.array([*topview.center_mm, 0.0])
    direction = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    corners = np.c_[topview.corners_mm, np.zeros(4)]

    def pose(d: float):
        return look_at(target + d * direction, target)

    if distance_mm is None:
        d = 0.5 * max(topview.width_mm, topview.height_mm)
        for _ in range(200):
            rvec, tvec = pose(d)
            uv = cv2.projectPoints(corners, rvec, tvec, K, np.asarray(dist, float))[0].reshape(-1, 2)
            span = max(np.ptp(uv[:, 0]) / w, np.ptp(uv[:, 1]) / h)
            inside = np.all((uv > [0.07 * w, 0.09 * h]) & (uv < [0.93 * w, 0.91 * h]))
            if inside and span <= fill:
                break
            d *= 1.03
        distance_mm = d
    rvec, tvec = pose(float(distance_mm))
    return CameraModel(
        K=K,
        dist=np.asarray(dist, float),
        image_size=(w, h),
        rvec=rvec,
        tvec=tvec,
        markers_mm=default_markers(topview),
    )
