"""Parts a height field cannot hold: the simulator's rays pass through windows and under bridges and overhangs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.errors import ConfigError
from layerwatch.simulate import PrintSimulator, camera_sim
from layerwatch.simulate.parts import blocks_part, window_part


@pytest.fixture(scope="module")
def wpart():
    return window_part()


def test_window_part_layers(wpart):
    assert wpart.n_layers == 70
    assert wpart.layers[-1].z == pytest.approx(14.0)
    # the bridge's deck is printed from 8 mm, spanning x -23..-7 (segments there, nothing at z <= 8 in the gap)
    for z, want in ((7.8, False), (8.2, True)):
        i = int(np.argmin(np.abs([la.z for la in wpart.layers] - np.float64(z))))
        sl = wpart.layer_slice(i)
        mid = (wpart.start[sl] + wpart.end[sl]) / 2
        in_gap = (mid[:, 0] > -18.5) & (mid[:, 0] < -11.5) & (np.abs(mid[:, 1]) < 2.5)
        assert in_gap.any() == want


def test_blocks_part_prints_each_block_per_layer_and_rejects_bad_blocks():
    tp = blocks_part([(0, 0, 4, 4, 0, 1)])
    assert tp.n_layers == 5 and tp.n_segments > 5 * 4
    for bad in ([], [(0, 0, 4, 4, 1, 1)], [(4, 0, 0, 4, 0, 1)], [(0, 0, 4, np.nan, 0, 1)], [(0, 0, 4, 4, -1, 1)]):
        with pytest.raises(ConfigError, match="blocks_part"):
            blocks_part(bad)


def _pixel(camera, p):
    uv = cv2.projectPoints(np.asarray([p], float), camera.rvec, camera.tvec, camera.K, camera.dist)[0]
    return np.round(uv.reshape(2)).astype(int)


def test_gaps_under_the_bridge_ledge_and_window_lintel(wpart, camera, topview):
    sim = PrintSimulator(wpart, camera, topview, seed=3)
    sim.advance(wpart.n_layers - 1)

    def gap_at(x, y):
        u, v = np.round(sim.grid.to_px(np.array([x, y], float))).astype(int)
        return sim.gap[v, u]

    assert gap_at(-15, 0) == pytest.approx([0.0, 8.0], abs=0.05)  # under the bridge
    assert gap_at(21, -5) == pytest.approx([0.0, 7.0], abs=0.05)  # under the ledge
    lo, hi = gap_at(5, -7.2)  # the window: from its sill to the lintel
    assert lo == pytest.approx(5.0, abs=0.15) and hi == pytest.approx(10.0, abs=0.05)
    assert gap_at(-21, 0)[1] == 0.0 and gap_at(5, 0)[1] == 0.0  # a pillar, the box's floor: solid


@pytest.mark.parametrize("point", [(-15.0, 0.0, 0.0), (21.0, -5.0, 0.0)], ids=["bridge", "ledge"])
def test_camera_sees_the_bed_under_a_bridge_and_an_overhang(wpart, camera, topview, monkeypatch, point):
    """The bed point under the bridge's deck / the ledge is grey bed, not the orange filament of a height field."""
    u, v = _pixel(camera, point)
    seen = PrintSimulator(wpart, camera, topview, seed=3).frame(wpart.n_layers - 1).photo
    monkeypatch.setattr(camera_sim, "_GAP_LAYERS", 1e9)  # no gaps: a plain height field
    solid = PrintSimulator(wpart, camera, topview, seed=3).frame(wpart.n_layers - 1).photo
    win = (slice(v - 1, v + 2), slice(u - 1, u + 2))

    def orange(photo):  # red minus blue (BGR): the filament is orange, the bed grey
        return float(photo[win][..., 2].astype(int).mean() - photo[win][..., 0].astype(int).mean())

    assert orange(seen) < 15 and orange(solid) > 40
