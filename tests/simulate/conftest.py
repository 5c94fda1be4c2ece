"""Small fixtures for the simulator tests (a synthetic block, a posed 640x360 camera)."""

from __future__ import annotations

import pytest

from layerwatch.geometry.topview import TopView
from layerwatch.simulate import default_camera
from layerwatch.simulate.parts import box_part


@pytest.fixture(scope="session")
def topview() -> TopView:
    return TopView(6.67, 90.0, 90.0, (0.0, 0.0))


@pytest.fixture(scope="session")
def camera(topview):
    return default_camera(topview, image_size=(640, 360))


@pytest.fixture(scope="session")
def part():
    return box_part(size_mm=30.0, height_mm=3.0, layer_h=0.3)


@pytest.fixture(scope="session")
def tall_part():
    return box_part(size_mm=24.0, height_mm=12.0, layer_h=0.4, fin=False)
