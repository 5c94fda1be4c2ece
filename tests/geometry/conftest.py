"""Fixtures for the geometry tests: an independent posed camera and synthetic bed photos."""

from __future__ import annotations

import pytest
from geometry_scenes import posed_camera

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView


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
