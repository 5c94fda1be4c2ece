"""Fixtures for the geometry tests: an independent posed camera and synthetic bed photos."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView


def posed_camera(size=(960, 540), hfov_deg=65.0, eye=(0.0, -170.0, 190.0), target=(0.0, 0.0, 0.0),
                 dist=(-0.08, 0.02, 0.0, 0.0, 0.0)) -> CameraModel:
    """A camera at ``eye`` (bed mm) looking at ``target``; built here, independently of the code under test."""
    w, h = size
    f = (w / 2) / np.tan(np.deg2rad(hfov_deg) / 2)
    K = np.array([[f, 0, (w - 1) / 2 + 3.0], [0, f * 1.002, (h - 1) / 2 - 2.0], [0, 0, 1]])
    fwd = np.subtract(target, eye).astype(float)
    fwd /= np.linalg.norm(fwd)
    x = np.cross(fwd, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(fwd, x)
    R = np.stack([x, y, fwd])
    return CameraModel(K=K, dist=np.array(dist), image_size=size,
                       rvec=cv2.Rodrigues(R)[0].ravel(), tvec=-R @ np.asarray(eye, float))


def rotation_error_deg(a: CameraModel, b: CameraModel) -> float:
    c = (np.trace(a.R.T @ b.R) - 1) / 2
    return float(np.rad2deg(np.arccos(np.clip(c, -1, 1))))


@pytest.fixture(scope="session")
def topview() -> TopView:
    return TopView(6.67, 90.0, 90.0, (0.0, 0.0))


@pytest.fixture(scope="session")
def camera() -> CameraModel:
    return posed_camera()


@pytest.fixture(scope="session")
def bed_photo(camera, topview):
    from layerwatch.geometry.synthetic import render_bed_scene

    return render_bed_scene(camera, topview.corners_mm, 6.0, texture="pei", noise=3.0, blur=1.0,
                            supersample=2, seed=4)
