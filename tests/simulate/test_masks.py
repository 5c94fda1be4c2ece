"""Truth masks checked against independent rasterisations (KD-tree samples, analytic squares).

The truth is what the camera sees of a failure (``simulate/truth.py``): a hole's near rim hides a
strip of it, a shifted block's walls facing the camera add to its bands; so the masks are compared
with the nominal footprints within those margins.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from layerwatch.errors import ConfigError
from layerwatch.gcode.toolpath import FEATURES
from layerwatch.simulate import Failure, simulate_layer
from layerwatch.simulate.raster import capsule_mask


def _pixel_centres_mm(tv):
    h, w = tv.shape
    vv, uu = np.mgrid[0:h, 0:w]
    return tv.to_mm(np.stack([uu, vv], -1).astype(float))


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


def test_infill_patch_mask_is_removed_footprint(part, camera, topview):
    centre, size, layer = (2.0, -3.0), 8.0, 5
    f = Failure("infill_defect", onset=layer, size_mm=size, center_mm=centre, seed=1)
    fr = simulate_layer(part, layer, camera, topview, [f], seed=0)
    # independent: sample the infill beads densely, keep samples inside the patch disc,
    # mark pixels within half a bead width of a kept sample
    sl = part.layer_slice(layer)
    inf = part.feature[sl] == FEATURES.index("infill")
    p0, p1, w = part.start[sl][inf], part.end[sl][inf], part.width[sl][inf]
    t = np.linspace(0, 1, 4000)[None, :, None]
    pts = (p0[:, None] + t * (p1 - p0)[:, None]).reshape(-1, 2)
    keep = np.linalg.norm(pts - centre, axis=1) <= size / 2
    tree = cKDTree(pts[keep])
    d, _ = tree.query(_pixel_centres_mm(topview).reshape(-1, 2))
    expected = (d <= float(w[0]) / 2).reshape(topview.shape)
    assert fr.truth is not None and fr.meta["failed"]
    # seen: inside the removed beads (one pixel of rounding), most of them (the near rim hides a strip)
    near = cv2.dilate(expected.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert (fr.truth & ~near).sum() <= 0.01 * expected.sum()
    assert (fr.truth & expected).sum() >= 0.5 * expected.sum(), (fr.truth.sum(), expected.sum())
    # the region version covers the whole patch disc
    disc = np.linalg.norm(_pixel_centres_mm(topview) - centre, axis=-1) <= size / 2 - 0.5
    assert (fr.truth_area & disc).sum() >= 0.97 * disc.sum()


def test_infill_patch_is_missing_in_height_field(part, camera, topview):
    from layerwatch.simulate import PrintSimulator

    f = Failure("infill_defect", onset=4, size_mm=8.0, center_mm=(0.0, 0.0), seed=1)
    sim = PrintSimulator(part, camera, topview, [f])
    sim.advance(4)
    v, u = np.round(sim.grid.to_px(np.array([0.0, 0.0]))).astype(int)[::-1]
    patch = sim.h[v - 5 : v + 6, u - 5 : u + 6]
    assert patch.max() <= part.layers[3].z + 0.05  # layer 4 missing there
    clean = PrintSimulator(part, camera, topview, [])
    clean.advance(4)
    assert clean.h[v - 5 : v + 6, u - 5 : u + 6].max() > part.layers[3].z + 0.1


def test_layer_shift_mask_is_shifted_area_xor(part, camera, topview):
    dx, dy = 3.0, -2.0
    f = Failure("layer_shift", onset=3, size_mm=3.6, offset_mm=(dx, dy), seed=2)
    fr = simulate_layer(part, 6, camera, topview, [f])
    xy = _pixel_centres_mm(topview)
    half = 15.0 + 0.225  # outer bead edge of the 30 mm block

    def area(ox, oy):
        block = (np.abs(xy[..., 0] - ox) <= half) & (np.abs(xy[..., 1] - oy) <= half)
        fx = 15.0 + 6.0 - 0.225  # the fin beside the block
        fin = (xy[..., 0] - ox >= fx) & (xy[..., 0] - ox <= fx + 0.9) & (
            np.abs(xy[..., 1] - oy) <= 6.225
        )
        return block | fin

    expected = area(dx, dy) ^ area(0, 0)
    assert _iou(fr.truth, expected) > 0.7  # plus the shifted layers' walls facing the camera
    k = int(round(1.5 * topview.px_per_mm)) | 1  # at most 1.5 mm off: the walls are 1.2 mm tall
    near = cv2.dilate(expected.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    assert (fr.truth & ~near).sum() <= 0.05 * fr.truth.sum()
    assert (fr.truth & expected).sum() >= 0.8 * expected.sum()
    # the failed region is the same two bands: the 3 mm closing of patch failures would join them across
    # the block (where the layer is where it should be)
    assert (fr.truth_area == fr.truth).all()
    before = simulate_layer(part, 2, camera, topview, [f])
    assert before.truth is None and not before.meta["failed"]


def test_thin_wall_mask_on_the_fin(part, camera, topview):
    f = Failure("thin_wall", onset=4, size_mm=6.0, seed=3)
    fr = simulate_layer(part, 4, camera, topview, [f])
    xy = _pixel_centres_mm(topview)[fr.truth]
    assert len(xy) > 50
    assert xy[:, 0].min() > 20.0  # on the fin (x ~ 21..22 mm), not the block


def test_foreign_body_mask_covers_the_object(part, camera, topview):
    f = Failure("foreign_body", onset=3, size_mm=8.0, center_mm=(0.0, 0.0), seed=5)
    fr = simulate_layer(part, 5, camera, topview, [f])
    from layerwatch.simulate.failures import resolve

    caps = resolve(f, part).capsules
    foot = capsule_mask(caps[:, 0:2], caps[:, 2:4], caps[:, 4] * 0.9, topview)
    assert (fr.truth_area & foot).sum() >= 0.95 * foot.sum()
    assert fr.truth.sum() < 6 * foot.sum()


@pytest.mark.parametrize("kind", ["spaghetti", "detachment"])
def test_other_failures_have_masks(kind, part, camera, topview):
    f = Failure(kind, onset=4, size_mm=12.0 if kind == "spaghetti" else 3.0, seed=7)
    fr = simulate_layer(part, 6, camera, topview, [f])
    clean = simulate_layer(part, 6, camera, topview, [])
    assert fr.meta["failed"] and fr.truth.sum() > 100
    changed = np.abs(fr.photo.astype(int) - clean.photo.astype(int)).max(-1) > 40
    assert changed.sum() > 150


def test_bad_failures_are_config_errors(part, camera, topview):
    with pytest.raises(ConfigError):
        Failure("melted", onset=1)
    with pytest.raises(ConfigError):
        simulate_layer(part, 1, camera, topview, [Failure("spaghetti", onset=500)])
    with pytest.raises(ConfigError):
        simulate_layer(part, 99, camera, topview)
