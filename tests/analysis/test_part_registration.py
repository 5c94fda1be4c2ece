"""Registration of the part's top layer (analysis/part_registration.py): the self-similarity refusal.

A layer of regular infill looks like itself moved by the infill's period, so when a defect weakens the
zero-shift peak, a peak at such a shift can pass for a layer shift. A move weaker than the zero-shift peak
is refused when the layer's own edges, shifted by it, match themselves at least as well as the peak's share.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from analysis_scenes import TOPVIEW
from report_case import report_case

from layerwatch.analysis.part_registration import (
    MOVE_MAX_MM,
    edges,
    mask_box,
    pad_box,
    part_motion,
    self_similarity,
)

S = TOPVIEW.px_per_mm


def _grid_layer(period_mm: float, angles=(45.0, -45.0), seed: int = 0) -> np.ndarray:
    """A 20 x 16 mm layer of straight infill lines ``period_mm`` apart at ``angles`` inside two walls, uint8 (0 = bed)."""
    h, w = TOPVIEW.shape
    (u0, v1), (u1, v0) = TOPVIEW.to_px(np.array([[100.0, 92.0], [120.0, 108.0]])).round().astype(int)
    layer = np.zeros((h, w), np.uint8)
    layer[v0:v1, u0:u1] = 150
    yy, xx = np.mgrid[0:h, 0:w]
    for a in angles:
        t = np.radians(a)
        layer[((xx * np.cos(t) + yy * np.sin(t)) % (period_mm * S) < 2.5) & (layer > 0)] = 220
    cv2.rectangle(layer, (u0, v0), (u1 - 1, v1 - 1), 240, 2)
    return layer


def _photo(grey: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur(grey.astype(np.float32), (3, 3), 0.8) + rng.normal(0, 2.0, grey.shape)
    return np.clip(g, 0, 255).astype(np.uint8)


def _layer_edges(layer: np.ndarray) -> np.ndarray:
    """The registered crop's layer edges as :func:`part_motion` forms them (footprint widened by 1 mm)."""
    foot = layer > 0
    box = pad_box(mask_box(foot), int(round(MOVE_MAX_MM * S)), foot.shape)
    k = int(round(S)) * 2 + 1
    top_layer = cv2.GaussianBlur(cv2.dilate(foot[box].astype(np.uint8), np.ones((k, k), np.uint8)).astype(np.float32),
                                 (0, 0), 2.0)
    ref = np.where(foot, layer, 60).astype(np.uint8)
    return edges(ref[box]) * top_layer


def test_self_similarity_peaks_again_at_the_infills_period_and_is_low_for_walls_moved_off_themselves():
    a = _layer_edges(_grid_layer(3.0, angles=(0.0,)))  # lines across x, 3 mm apart
    assert self_similarity(a, 0.0, 0.0) == pytest.approx(1.0)
    assert self_similarity(a, 3.0 * S, 0.0) > self_similarity(a, 1.5 * S, 0.0) + 0.1
    walls = _layer_edges(_grid_layer(3.0, angles=()))  # no infill: the walls moved 2 mm diagonally miss themselves
    assert self_similarity(walls, 1.4 * S, 1.4 * S) < 0.1
    assert self_similarity(np.zeros_like(a), 3.0 * S, 0.0) == 0.0


def test_a_real_2_mm_shift_of_a_periodic_layer_over_its_unmoved_layers_is_still_measured():
    """The shifted layer lies over the layers below, the same infill at the plan's place: their zero-shift peak is
    strong, the move's peak may be weaker, and the layer does not look like itself 2 mm away."""
    layer = _grid_layer(3.0)
    h, w = layer.shape
    ref = np.where(layer > 0, layer, 60).astype(np.uint8)
    below = np.where(layer > 0, _grid_layer(3.0, angles=(45.0,)), 60).astype(np.uint8)  # the layer below: one direction
    for shift in ((2.0, 0.0), (0.0, -2.0), (1.5, 1.5)):
        M = np.float32([[1, 0, shift[0] * S], [0, 1, -shift[1] * S]])
        moved = cv2.warpAffine(layer, M, (w, h), flags=cv2.INTER_NEAREST)
        top = _photo(np.where(moved > 0, moved, below), 1)
        m = part_motion(top, ref, layer > 0, TOPVIEW)
        assert m.moved and np.hypot(m.dx_mm - shift[0], m.dy_mm - shift[1]) < 0.5


@pytest.mark.slow
def test_an_infill_defect_of_the_simplify3d_part_does_not_register_as_a_layer_shift(shared_data):
    """The cross-part evaluation's Simplify3D infill defect s017 (seed 0, 200 layers, beside share 0.3), its first
    layer: the missing infill weakens the zero-shift peak and a peak 1.2 mm away (0.6 of it) was taken as a layer
    shift, yet the layer's own edges shifted 1.2 mm match themselves 0.71: that peak is the layer's pattern."""
    sim, pipe, layers = report_case(shared_data / "gcode" / "simplify3d-4.1.2_zlift.gcode", "s017-infill_defect")
    for i in layers[:2]:
        res = pipe.process(sim.frame(i).photo, i)
    assert res.regions, "the defect is seen"
    assert not [r.kind for r in (*res.regions, *res.outside_regions) if r.kind in ("layer_shift", "detachment")]
