"""Per-layer plane homographies between the camera image and the top view.

For a layer whose top surface lies in the bed plane ``Z = z`` the pinhole
projection of the paper's eq. (1), ``s [u v 1]^T = K [R | t] [X Y Z 1]^T``,
reduces to a homography of the plane coordinates ``(X, Y)`` because the third
column of ``R`` only multiplies the constant ``z`` (eq. 3)::

    H_img_from_plane(z) = K [r1  r2  r3 * z + t]                       (eq. 3)

and the top view is the image of the same plane under the fixed affine
``top_from_bed`` of :class:`~layerwatch.geometry.topview.TopView` (eq. 2), so::

    top_from_image(z) = top_from_bed @ inv(H_img_from_plane(z))        (eqs. 1-2)

All image coordinates here are *undistorted* pixels of ``camera.image_size``;
lens distortion is handled by :mod:`layerwatch.geometry.warp`.

References
----------
Petsiuk & Pearce (2022), Section 2.3, eqs. (1)-(3).
"""

from __future__ import annotations

import numpy as np

from layerwatch.errors import CalibrationError, WarpError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView

__all__ = ["image_from_plane", "top_from_image", "image_from_top", "apply_homography"]


def image_from_plane(camera: CameraModel, z: float) -> np.ndarray:
    """Homography, shape (3, 3), bed-plane mm ``(X, Y, 1)`` at height ``z`` -> undistorted image px.

    Parameters
    ----------
    camera : CameraModel
        Must have a pose (``rvec``, ``tvec``: ``camera_from_bed``).
    z : float
        Height of the plane above the bed, mm.

    References
    ----------
    Petsiuk & Pearce (2022), eq. (3): ``K [r1 r2 r3 Z + t]``.
    """
    if not camera.has_pose:
        raise CalibrationError(
            "the camera model has no bed pose yet: run `layerwatch calibrate --markers PHOTO`."
        )
    if not np.isfinite(z):
        raise WarpError(f"layer height z={z} is not a finite number; pass the layer's Z in mm.")
    R = camera.R
    t = np.asarray(camera.tvec, dtype=np.float64)
    M = np.column_stack([R[:, 0], R[:, 1], R[:, 2] * float(z) + t])
    return camera.K @ M


def top_from_image(camera: CameraModel, topview: TopView, z: float) -> np.ndarray:
    """Homography, shape (3, 3), undistorted image px -> top-view px of the plane ``Z = z``.

    ``top_from_image = topview.top_from_bed @ inv(K [r1 r2 r3 z + t])``,
    normalised so that element ``[2, 2]`` is 1 when possible.

    References
    ----------
    Petsiuk & Pearce (2022), eqs. (1)-(3).
    """
    H_ip = image_from_plane(camera, z)
    if abs(np.linalg.det(H_ip)) < 1e-12 * np.abs(H_ip).max() ** 3:
        raise WarpError(
            f"the plane Z={z:g} mm passes through the camera centre; check the layer height and the pose."
        )
    H = topview.top_from_bed @ np.linalg.inv(H_ip)
    return H / H[2, 2] if abs(H[2, 2]) > 1e-12 else H


def image_from_top(camera: CameraModel, topview: TopView, z: float) -> np.ndarray:
    """Inverse of :func:`top_from_image`, shape (3, 3): top-view px -> undistorted image px."""
    H = image_from_plane(camera, z) @ topview.bed_from_top
    return H / H[2, 2] if abs(H[2, 2]) > 1e-12 else H


def apply_homography(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Map points ``(..., 2)`` through the homography ``H`` (3, 3); returns float64 ``(..., 2)``."""
    p = np.asarray(pts, dtype=np.float64)
    q = p @ H[:, :2].T + H[:, 2]
    return q[..., :2] / q[..., 2:3]
