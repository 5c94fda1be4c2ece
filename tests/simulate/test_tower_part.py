"""The soak's tall part and its G-code writer (benchmarks/bench_soak.py)."""

import numpy as np

from layerwatch.gcode import read_toolpath
from layerwatch.simulate.parts import toolpath_gcode, tower_part


def test_tower_part_has_its_layers_and_a_boss_above_the_block():
    tp = tower_part(height_mm=12.0, layer_h=0.2, boss_from_mm=8.0, solid_layers=2)
    assert tp.n_layers == 60
    assert np.isclose(tp.layers[-1].z, 12.0)
    low, high = tp.layer_slice(10), tp.layer_slice(55)
    span = lambda sl: np.ptp(np.concatenate([tp.start[sl], tp.end[sl]]), axis=0)  # noqa: E731
    assert (span(low) > 25).all() and (span(high) < 20).all()  # 30 mm block, then the 18 mm boss


def test_toolpath_gcode_round_trips_through_the_reader():
    tp = tower_part(height_mm=4.0, layer_h=0.2, boss_from_mm=2.0, solid_layers=1)
    back = read_toolpath(toolpath_gcode(tp))
    assert back.n_layers == tp.n_layers
    assert back.n_segments == tp.n_segments
    np.testing.assert_allclose(back.start, tp.start, atol=1e-3)
    np.testing.assert_allclose(back.end, tp.end, atol=1e-3)
    np.testing.assert_allclose(back.width, tp.width, atol=1e-3)
