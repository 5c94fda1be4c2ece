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


def _deck_photo(camera, topview, slit_depth_mm):
    """A 12 x 12 mm deck 0.2 mm thick over 8 mm of air with a one-cell slit along X, ``slit_depth_mm`` deep; grey photo."""
    from layerwatch.geometry.topview import TopView
    from layerwatch.simulate.photo import Photographer
    from layerwatch.simulate.settings import SimSettings

    st = SimSettings(light_jitter_mm=0.0, light_intensity_jitter=0.0, exposure_drift=0.0, colour_drift=0.0,
                     read_noise=0.0, shot_noise=0.0, blur_px=(0.5, 0.5))
    grid = TopView(st.grid_px_per_mm, topview.width_mm + 20, topview.height_mm + 20, topview.center_mm)
    h = np.zeros(grid.shape, np.float32)
    (u0, v1), (u1, v0) = np.round(grid.to_px(np.array([[-6.0, -6.0], [6.0, 6.0]]))).astype(int)
    h[v0:v1, u0:u1] = 8.2
    (su0, sv), (su1, _) = np.round(grid.to_px(np.array([[-3.0, 0.0], [3.0, 0.0]]))).astype(int)
    h[sv, su0:su1] = 8.2 - slit_depth_mm
    mat = (h > 0).astype(np.uint8)
    gap = np.zeros((*h.shape, 2), np.float32)
    gap[h > 8.1, 1] = 8.0  # the deck's cells are printed over air
    photo, _ = Photographer(camera, topview, grid, st, seed=1).shoot(h, mat, 0, 0.2, gap)
    return cv2.cvtColor(photo, cv2.COLOR_BGR2GRAY).astype(float)


def test_a_hairline_slit_over_air_is_not_a_dark_dash(camera, topview, monkeypatch):
    """A one-cell slit between two beads of a bridge's deck looks like one over the layer below, not like a dark dash.

    The height field's slit is the grid's rendering of a sub-cell gap from the
    beads' jitter; how deep the air under it is must not tilt the tops of the beads
    beside it (it did: central differences across 8 mm made both neighbours
    near-vertical, a dark dash that the HOG comparison flagged on clean bridges).
    """
    from layerwatch.simulate import photo as photo_mod

    us, vs = zip(*(_pixel(camera, (x, y, 8.2)) for x in (-2.5, 2.5) for y in (-0.6, 0.6)), strict=True)
    win = (slice(min(vs), max(vs) + 1), slice(min(us), max(us) + 1))

    def darker(depth):  # how much darker the slit's surroundings are than with a one-layer groove
        return float(_deck_photo(camera, topview, 0.2)[win].mean() - _deck_photo(camera, topview, depth)[win].mean())

    assert darker(8.2) < 4.0  # the slit itself, 1 cell of 3
    monkeypatch.setattr(photo_mod, "_SLIT_LAYERS", 1e9)  # normals across the slit as before
    assert darker(8.2) > 10.0
