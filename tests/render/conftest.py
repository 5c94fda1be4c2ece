"""Fixtures of the render tests: small synthetic parts and top views."""

from __future__ import annotations

import pytest
from render_parts import square_part, thin_wall_part

from layerwatch.geometry.topview import TopView


@pytest.fixture(scope="module")
def small_view() -> TopView:
    return TopView(6.67, 30.0, 30.0, (5.0, -3.0))


@pytest.fixture(scope="module")
def part():
    """Solid 20 mm square, 4 layers of 0.3 mm, +-45 deg infill."""
    return square_part(4, center=(5.0, -3.0), size=20.0)


@pytest.fixture(scope="module")
def wall():
    return thin_wall_part(3, center=(5.03, -2.94), length=20.0)  # off the pixel grid
