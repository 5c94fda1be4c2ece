"""The volume march with its rays' steps computed a row at a time gives the march before it, float for float."""

from __future__ import annotations

import numpy as np
import pytest
from march_before import march_volume_before
from test_volume import _job

from layerwatch.render import volume
from layerwatch.render.fast import StackRenderer
from layerwatch.render.settings import RenderSettings
from layerwatch.simulate import default_camera


def _compare_every_layer(tp, tv, cams, monkeypatch) -> int:
    """Render every layer from each camera centre; each march's image and hit heights against the frozen march."""
    real = volume._march_volume
    seen = []

    def both(*a):
        real(*a)
        out, hit = np.empty_like(a[16]), np.empty_like(a[17])
        march_volume_before(*a[:16], out, hit, a[18])
        np.testing.assert_array_equal(a[16], out)
        np.testing.assert_array_equal(a[17], hit)
        seen.append(1)

    monkeypatch.setattr(volume, "_march_volume", both)
    for cam in cams:
        r = StackRenderer(tp, tv, RenderSettings(reference="volume"))
        for index in range(tp.n_layers):
            r.render(index, cam)
    return len(seen)


def test_rows_march_as_before_on_the_example_part_from_three_cameras(shared_data, monkeypatch):
    """In front of the printer (the simulator's camera), right above a top-view pixel (a ray of length 0:
    the plane point itself) and above the view's corner."""
    tp, tv = _job("example", shared_data)
    front = default_camera(tv).center_mm
    above = np.array([*tv.to_mm(np.array([300.0, 200.0])), 150.0])  # an integer pixel: its ray has no length
    assert np.allclose(tv.to_px(above[:2]), [300.0, 200.0])
    corner = np.array([*tv.to_mm(np.array([0.0, 0.0])), 120.0])
    assert _compare_every_layer(tp, tv, [front, above, corner], monkeypatch) == 3 * tp.n_layers


@pytest.mark.slow
@pytest.mark.parametrize("source", ["prusaslicer-2.8.1_mini-cube_ascii.gcode", "cura-4.10.0_m83_multi-object.gcode"])
def test_rows_march_as_before_on_slicers_files(source, shared_data, monkeypatch):
    tp, tv = _job(source, shared_data)
    assert _compare_every_layer(tp, tv, [default_camera(tv).center_mm], monkeypatch) == tp.n_layers
