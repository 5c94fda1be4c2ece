"""The camera-footprint blur of references (render/camera_match.py)."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.render.camera_match import footprint_covariance, match_camera


def _camera(tilt_deg: float) -> CameraModel:
    import cv2

    # Start looking straight down (R = diag(1, -1, -1)), then tilt about bed X.
    R0 = np.diag([1.0, -1.0, -1.0])
    a = np.deg2rad(tilt_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    R = R0 @ Rx.T
    C = np.array([0.0, -300.0 * np.sin(a), 300.0 * np.cos(a)])
    return CameraModel(
        K=[[1000, 0, 639.5], [0, 1000, 359.5], [0, 0, 1]],
        dist=np.zeros(5),
        image_size=(1280, 720),
        rvec=cv2.Rodrigues(R)[0].ravel(),
        tvec=-R @ C,
    )


def test_nadir_camera_footprint_is_isotropic_scale_ratio():
    tv = TopView()
    cov = footprint_covariance(_camera(0.0), tv, 0.0, psf_px=1.0)
    # camera: 1000 px / 300 mm = 3.33 px/mm; top view 6.67 px/mm -> 2.0 top px per camera px
    assert cov == pytest.approx(np.diag([4.0, 4.0]) * (6.67 / (1000 / 300)) ** 2 / 4.0, rel=1e-3)


def test_oblique_camera_footprint_is_elongated_along_view():
    tv = TopView()
    cov = footprint_covariance(_camera(45.0), tv, 0.0, psf_px=1.0)
    # foreshortening stretches the footprint along bed Y (image rows) by ~1/cos(45)
    assert cov[1, 1] / cov[0, 0] == pytest.approx(2.0, rel=0.05)


def test_match_camera_blurs_but_keeps_mean_and_dtype():
    rng = np.random.default_rng(0)
    ref = (rng.random((120, 120)) > 0.5).astype(np.uint8) * 255
    out = match_camera(ref, _camera(45.0), TopView(width_mm=18, height_mm=18), 0.0)
    assert out.dtype == np.uint8 and out.shape == ref.shape
    assert abs(float(out.mean()) - float(ref.mean())) < 3.0
    assert out.std() < ref.std() * 0.8  # high frequencies removed
