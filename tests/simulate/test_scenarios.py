"""Scenario sampling, failure activity windows, under-extrusion, frame files."""

from __future__ import annotations

import json

import cv2
import numpy as np

from layerwatch.simulate import (
    FAILURE_TYPES,
    Failure,
    Scenario,
    random_scenarios,
    save_frame,
    simulate_layer,
    simulate_print,
    thin_wall_segments,
)
from layerwatch.simulate.failures import DEFAULT_DURATION


def test_random_scenarios_cover_types_and_valid_onsets(part):
    sc = random_scenarios(part, 21, seed=4)
    assert len(sc) == 21
    labels = [s.label for s in sc]
    assert labels.count("clean") == 3
    assert set(labels) == set(FAILURE_TYPES) | {"clean"}
    for s in sc:
        for f in s.failures:
            assert 2 <= f.onset < part.n_layers
            if f.type == "thin_wall":
                assert thin_wall_segments(part, f.onset).sum() >= 3
    again = random_scenarios(part, 21, seed=4)
    assert [s.failures for s in again] == [s.failures for s in sc]
    assert [s.failures for s in random_scenarios(part, 21, seed=5)] != [s.failures for s in sc]


def test_thin_wall_segments_find_the_fin_only(part):
    sl = part.layer_slice(3)
    thin = thin_wall_segments(part, 3)
    mid = 0.5 * (part.start[sl] + part.end[sl])[thin]
    assert len(mid) >= 2
    assert np.all(mid[:, 0] > 20.0)  # the fin stands at x = 21 mm; the block ends at 15


def test_patch_failures_heal_after_their_duration(part, camera, topview):
    dur = DEFAULT_DURATION["infill_defect"]
    f = Failure("infill_defect", onset=3, size_mm=8.0, center_mm=(0.0, 0.0))
    assert [f.active(i) for i in range(2, 3 + dur + 1)] == [False] + [True] * dur + [False]
    f = Failure("infill_defect", onset=3, size_mm=8.0, center_mm=(0.0, 0.0), duration=2)
    frames = list(simulate_print(part, camera, topview, Scenario((f,), "x"), layers=[2, 3, 4, 5]))
    assert [fr.truth is None for fr in frames] == [True, False, False, True]


def test_under_extrusion_keeps_thin_beads(part, camera, topview):
    from layerwatch.simulate import PrintSimulator

    kw = dict(onset=4, size_mm=8.0, center_mm=(0.0, 0.0))
    miss = PrintSimulator(part, camera, topview, [Failure("infill_defect", mode="missing", **kw)])
    under = PrintSimulator(part, camera, topview, [Failure("infill_defect", mode="under", **kw)])
    f_miss, f_under = miss.frame(4), under.frame(4)
    assert np.array_equal(f_miss.truth, f_under.truth)
    v, u = np.round(miss.grid.to_px(np.array([0.0, 0.0]))).astype(int)[::-1]
    z3 = part.layers[3].z
    assert miss.h[v - 8 : v + 9, u - 8 : u + 9].max() <= z3 + 0.05
    assert under.h[v - 8 : v + 9, u - 8 : u + 9].max() > z3 + 0.02


def test_save_frame_writes_photo_masks_meta(part, camera, topview, tmp_path):
    fr = simulate_layer(part, 4, camera, topview, [Failure("foreign_body", onset=3, seed=1)])
    paths = save_frame(fr, tmp_path)
    assert cv2.imread(str(paths["photo"])).shape == fr.photo.shape
    assert (cv2.imread(str(paths["truth"]), cv2.IMREAD_GRAYSCALE) > 0).sum() == fr.truth.sum()
    meta = json.loads(paths["meta"].read_text())
    assert meta["layer"] == 4 and meta["failures"] == ["foreign_body"] and meta["failed"]
