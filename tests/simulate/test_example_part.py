"""The simulator on the bundled PrusaSlicer example (needs layerwatch.gcode.read_toolpath)."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.geometry.topview import TopView
from layerwatch.simulate import (
    FAILURE_TYPES,
    default_camera,
    random_scenarios,
    simulate_layer,
    thin_wall_segments,
)


@pytest.fixture(scope="module")
def example(example_gcode):
    gcode = pytest.importorskip("layerwatch.gcode")
    if not hasattr(gcode, "read_toolpath"):
        pytest.skip("layerwatch.gcode.read_toolpath is not available yet")
    tp = gcode.read_toolpath(example_gcode)
    tv = TopView(6.67, 90.0, 90.0, (110.0, 100.0))
    return tp, tv, default_camera(tv, image_size=(640, 360))


@pytest.mark.slow
def test_example_has_thin_walls_and_every_failure_shows(example):
    tp, tv, cam = example
    assert any(thin_wall_segments(tp, i).sum() >= 3 for i in range(10, tp.n_layers))
    scen = random_scenarios(tp, 7, seed=3, clean_fraction=0.0)
    assert {s.label for s in scen} == set(FAILURE_TYPES)
    for s in scen:
        f = s.failures[0]
        idx = min(f.onset + 2, tp.n_layers - 1)
        fr = simulate_layer(tp, idx, cam, tv, s.failures, seed=1)
        clean = simulate_layer(tp, idx, cam, tv, (), seed=1)
        assert fr.meta["failed"], s.label
        changed = np.abs(fr.photo.astype(int) - clean.photo.astype(int)).max(-1) > 40
        assert changed.sum() > 20, s.label
