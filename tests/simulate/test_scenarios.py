"""Scenario sampling, failure activity windows, under-extrusion, frame files."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

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
    # the thin beads lie over half a layer below the plan: seen as the same hole, within a pixel
    near = cv2.dilate(f_miss.truth.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert (f_under.truth & ~near).sum() <= 0.01 * f_miss.truth.sum()
    assert (f_under.truth & f_miss.truth).sum() >= 0.5 * f_miss.truth.sum()
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


@pytest.mark.slow
def test_one_object_detaching_leaves_the_others_as_printed_before_the_onset(shared_data):
    """``Failure(within_mm=...)``: the plate's other objects are drawn as in the clean print, also one that
    starts on a higher layer, over air (ideamaker's plate: two objects from layer 18); they were drawn
    without their gaps, so the photos differed from the clean print's before the onset (an 'early' stop
    at layer 19 in the object-cancel evaluation)."""
    from layerwatch.evaluate.object_cancel import find_plates
    from layerwatch.pipeline.config import observed_square, resolve_config
    from layerwatch.simulate import PrintSimulator, default_camera

    name = "ideamaker-4.2.0_multi-object.gcode"
    tp, om = find_plates(shared_data / "gcode", [name])[name]
    boxes = np.array([o.bbox_mm for o in om.objects])
    box = (boxes[:, 0].min(), boxes[:, 1].min(), boxes[:, 2].max(), boxes[:, 3].max())
    tv = resolve_config(None, gcode=observed_square(box)).config.topview.topview()
    cam = default_camera(tv, image_size=(640, 360))
    x0, y0, x1, y1 = om.objects[0].bbox_mm
    fail = Failure("detachment", 20, 2.6, 3, within_mm=(x0 - 0.5, y0 - 0.5, x1 + 0.5, y1 + 0.5))
    one, clean = PrintSimulator(tp, cam, tv, [fail], seed=3), PrintSimulator(tp, cam, tv, [], seed=3)
    diff = np.abs(one.frame(19).photo.astype(int) - clean.frame(19).photo.astype(int)).sum(-1)
    assert (diff > 30).sum() == 0, int((diff > 30).sum())
    moved = np.abs(one.frame(20).photo.astype(int) - clean.frame(20).photo.astype(int)).sum(-1)
    assert (moved > 30).sum() > 50  # ... and the object moves from the onset


def _fine_block(tagged: bool = True):
    """A 10 mm square block whose perimeters are written as 0.5 mm pieces (KISSlicer, arc-welded
    files), with a 0.9 mm thick, 10 mm long fin 6 mm beside it; rectilinear infill on layers 0 and 2,
    none on layer 1 (infill printed every other layer, as Cura does). ``tagged=False``: no feature tags."""
    from layerwatch.gcode.toolpath import FEATURES, Toolpath

    ext, per, inf = (FEATURES.index(n) for n in ("external_perimeter", "perimeter", "infill"))

    def loop(x0, y0, x1, y1, step=0.5):
        pts = []
        for a, b in (((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))):
            n = max(int(round(np.hypot(b[0] - a[0], b[1] - a[1]) / step)), 1)
            t = np.linspace(0.0, 1.0, n + 1)
            pts.append(np.c_[a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])])
        p = np.concatenate([q[:-1] for q in pts])
        return p, np.roll(p, -1, axis=0)

    starts, ends, feats, zs = [], [], [], []
    for k in range(3):
        z = 0.3 * (k + 1)
        for off, code in ((0.0, ext), (0.45, per)):
            a, b = loop(off, off, 10.0 - off, 10.0 - off)
            starts.append(a), ends.append(b), feats.append(np.full(len(a), code))
        a, b = loop(16.0, 0.0, 16.9, 10.0)  # the fin: two beads thick, 6 mm off the block
        starts.append(a), ends.append(b), feats.append(np.full(len(a), ext))
        if k != 1:
            ys = np.arange(1.2, 9.0, 0.9)
            starts.append(np.c_[np.full(len(ys), 1.0), ys]), ends.append(np.c_[np.full(len(ys), 9.0), ys])
            feats.append(np.full(len(ys), inf))
        zs.append(np.full(sum(len(s) for s in starts) - sum(len(q) for q in zs), z))
    feature = np.concatenate(feats).astype(np.uint8)
    return Toolpath.from_segments(np.concatenate(starts), np.concatenate(ends), np.concatenate(zs), width=0.45,
                                  feature=feature if tagged else np.zeros_like(feature), layer_height=0.3)


def test_thin_walls_leave_out_a_thick_part_s_corners():
    tp = _fine_block()
    sl = tp.layer_slice(0)
    thin = thin_wall_segments(tp, 0)
    mid = 0.5 * (tp.start[sl] + tp.end[sl])
    # the fin's beads are a thin wall; none of the block's (its corner tips are thin too, but not walls)
    assert thin[mid[:, 0] > 12.0].mean() > 0.8
    assert not thin[mid[:, 0] < 11.0].any()


def test_infill_defect_removes_infill_only_where_the_file_marks_it():
    from layerwatch.simulate.failures import patch_layers, resolve

    tp, bare = _fine_block(), _fine_block(tagged=False)
    f = Failure("infill_defect", onset=0, size_mm=4.0, center_mm=(5.0, 1.0), duration=3)  # infill and a wall
    rf = resolve(f, tp)
    for i, infill in ((0, True), (1, False), (2, True)):
        assert rf.select[tp.layer_slice(i)].any() == infill  # a layer without infill loses nothing (its walls stay)
    assert patch_layers(rf, tp) == [0, 2]
    untagged = resolve(f, bare)  # no tags at all: any bead may be the infill
    assert untagged.select.all()
    assert patch_layers(untagged, bare) == [0, 1, 2]
    far = resolve(Failure("thin_wall", onset=0, size_mm=1.0, center_mm=(30.0, 30.0)), tp)
    assert patch_layers(far, tp) == []  # nothing selectable within the patch
