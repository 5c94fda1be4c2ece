"""Hidden ledges (analysis/ledges.py): lower floors no earlier photo showed are judged by the reference's HOG."""

from __future__ import annotations

import numpy as np
import pytest

import layerwatch.pipeline.step as step_module
from layerwatch.analysis.ledges import (
    LEDGE_SHARE,
    ledge_blocks,
    ledge_regions,
    slab_layers,
    slab_tops,
)
from layerwatch.errors import AnalysisError
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.toolpath import Layer
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera
from layerwatch.simulate.failures import MAT_TOOL, resolve

TV = TopView(6.67, 9.6, 9.6, (0.0, 0.0))  # 64 x 64 px: 7 x 7 blocks of 2 x 2 cells of 8 px


def test_ledge_blocks_are_those_whose_centre_tile_lies_mostly_on_the_ledges():
    ledges = np.zeros(TV.shape, bool)
    ledges[8:16, 8:16] = True  # exactly the tile of block (0, 0) (tiles start at 4 px... (2-1)*8//2 = 4)
    ledges[4:12, 20:28] = True  # the tile of block (0, 2): rows 4-12, columns 20-28
    got = ledge_blocks(ledges, (7, 7), 8, 2)
    assert got[0, 2] and not got[0, 0] and got.sum() == 1  # block (0, 0)'s tile is rows/cols 4-12: a quarter
    half = np.zeros(TV.shape, bool)
    half[4:12, 4:4 + int(8 * LEDGE_SHARE)] = True
    assert ledge_blocks(half, (7, 7), 8, 2)[0, 0]


def test_ledge_regions_report_low_blocks_on_the_ledges_outside_the_considered_ones():
    heat = np.ones((7, 7))
    heat[3, 3] = heat[3, 4] = 0.05  # on the ledges, not considered: a region
    heat[5, 5] = 0.05  # on the ledges but considered: eq. (5) counts it, not this figure
    heat[0, 0] = 0.05  # not on the ledges
    considered = np.zeros((7, 7), bool)
    considered[5, 5] = True
    ledges = np.zeros(TV.shape, bool)
    ledges[20:60, 20:60] = True
    regions = ledge_regions(heat, considered, ledges, 0.2, 8, 2, TV, 0.5)
    assert len(regions) == 1
    r = regions[0]
    assert r.area_mm2 == pytest.approx(2 * (8 / 6.67) ** 2) and r.outside_fraction == 1.0
    assert r.min_similarity == pytest.approx(0.05)
    assert ledge_regions(np.ones((7, 7)), considered, ledges, 0.2, 8, 2, TV, 0.5) == []


def test_ledge_regions_refuse_arrays_of_another_grid():
    with pytest.raises(AnalysisError, match="block grid"):
        ledge_regions(np.ones((7, 7)), np.zeros((6, 7), bool), np.zeros(TV.shape, bool), 0.2, 8, 2, TV, 0.5)
    with pytest.raises(AnalysisError, match="block grid"):
        ledge_regions(np.ones((7, 7)), np.zeros((7, 7), bool), np.zeros((10, 10), bool), 0.2, 8, 2, TV, 0.5)


def _example_pipeline():
    """The example part, a 1280 x 720 camera and a pipeline on its job file: ``(toolpath, camera, top view, pipe)``."""
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    cam = default_camera(cfg.topview.topview(), image_size=(1280, 720))
    cfg = cfg.for_camera(cam)
    return tp, cam, cfg.topview.topview(), LayerPipeline(tp, cam, cfg, memo=2)


@pytest.mark.slow
def test_single_photo_sees_an_object_on_the_plate_beside_the_top_layer():
    """Single-photo mode (the pipeline forgets the print before the photo: bed photo and reference only): a
    screw or lump on the example part's plate while the boss above it prints lay inside the printed body,
    which the bed photo cannot judge, and was missed; the reference's HOG on the plate finds it. The clean
    photo of the same layer reports nothing there."""
    tp, cam, tv, pipe = _example_pipeline()
    fb = Failure(type="foreign_body", onset=18, size_mm=8.0, center_mm=(110.0, 112.5), seed=3)
    layer = 19
    outside = {}
    for name, failures in (("clean", ()), ("object", (fb,))):
        sim = PrintSimulator(tp, cam, tv, failures, seed=4)
        pipe.new_print(sim.bed_photo())
        res = pipe.process(sim.frame(layer).photo, layer)
        assert res.status == "ok", res.message
        outside[name] = res
    assert outside["clean"].outside_anomalous_mm2 == 0
    found = outside["object"].outside_regions
    assert found and outside["object"].outside_anomalous_mm2 >= 4.0
    assert any(abs(r.centroid_mm[0] - 110.0) < 6 and abs(r.centroid_mm[1] - 112.5) < 6 for r in found)


def test_ledge_regions_join_off_colour_pixels_to_the_failing_tiles():
    considered = np.zeros((7, 7), bool)
    ledges = np.zeros(TV.shape, bool)
    ledges[8:56, 8:56] = True
    coloured = np.zeros(TV.shape, bool)
    coloured[30:36, 20:40] = True
    regions = ledge_regions(np.ones((7, 7)), considered, ledges, 0.2, 8, 2, TV, 0.5, coloured)
    assert len(regions) == 1 and regions[0].area_mm2 == pytest.approx(120 / 6.67**2)
    assert regions[0].mean_similarity == pytest.approx(0.1)
    with pytest.raises(AnalysisError, match="block grid"):
        ledge_regions(np.ones((7, 7)), considered, ledges, 0.2, 8, 2, TV, 0.5, np.zeros((10, 10), bool))


@pytest.mark.slow
def test_single_photo_sees_a_blue_hex_key_on_the_plate_by_its_colour(monkeypatch):
    """A blue hex key on the orange plate round the boss (the miss of the report's sample, issue 18): its
    blocks' gradient histograms barely change, so the HOG test alone marks under a third of it; the colour
    test marks most of it. The clean photo of the same layer stays quiet."""
    tp, cam, tv, pipe = _example_pipeline()
    layer = 19
    key = Failure(type="foreign_body", onset=18, size_mm=10.0, center_mm=(100.0, 112.5), seed=7)
    assert (resolve(key, tp).capsule_mat == MAT_TOOL).any()  # seed 7 lays the hex key

    def marked(res, truth):
        boxes = np.zeros(tv.shape, bool)
        for r in res.outside_regions:
            (u0, v0), (u1, v1) = tv.to_px(np.array([[r.bbox_mm[0], r.bbox_mm[3]], [r.bbox_mm[2], r.bbox_mm[1]]]))
            boxes[int(v0):int(v1) + 1, int(u0):int(u1) + 1] = True
        return float((boxes & truth).sum() / truth.sum())

    clean = PrintSimulator(tp, cam, tv, (), seed=4)
    pipe.new_print(clean.bed_photo())
    assert pipe.process(clean.frame(layer).photo, layer).outside_anomalous_mm2 == 0
    sim = PrintSimulator(tp, cam, tv, (key,), seed=4)
    frame = sim.frame(layer)
    pipe.new_print(sim.bed_photo())
    res = pipe.process(frame.photo, layer)
    assert res.status == "ok" and marked(res, frame.truth_area) > 0.6
    monkeypatch.setattr(step_module, "off_colour", lambda *a: None)  # the HOG test alone
    pipe.new_print(sim.bed_photo())
    assert marked(pipe.process(frame.photo, layer), frame.truth_area) < 0.35


def _layers(zs, heights):
    return [Layer(i, z, h, 0, 0, 0, 0, (0.0, 0.0, 1.0, 1.0), 1.0) for i, (z, h) in enumerate(zip(zs, heights, strict=True))]


def test_slab_layers_are_the_earlier_tops_above_the_layers_bottom():
    """KISSlicer's interleaved objects (0.263 / 0.278 mm steps): layer 3's slab (0.278-0.556 mm) holds layer 2's
    top (0.526 mm), layer 2's (0.263-0.526 mm) layer 1's (0.278 mm); a plain stack's previous layer lies at its
    bottom, not in it."""
    plate = _layers([0.263, 0.278, 0.526, 0.556], [0.263, 0.278, 0.263, 0.278])
    assert [slab_layers(plate, i) for i in range(4)] == [[], [0], [1], [2]]
    plain = _layers([0.2, 0.4, 0.6], [0.2, 0.2, 0.2])
    assert [slab_layers(plain, i) for i in range(3)] == [[], [], []]
    assert slab_layers(_layers([0.2, 0.3], [0.2, 0.0]), 1) == []  # thickness unknown: no slab


def test_slab_tops_are_the_earlier_footprints_the_layer_does_not_print_over():
    a, b, own = (np.zeros((8, 8), bool) for _ in range(3))
    a[0:3, 0:3] = True
    b[5:8, 5:8] = True
    own[2:6, 2:6] = True
    got = slab_tops([a, b], own)
    assert got.sum() == 9 + 9 - 1 - 1 and not (got & own).any()
    with pytest.raises(AnalysisError, match="slab layer"):
        slab_tops([np.zeros((4, 4), bool)], own)


def test_ledge_regions_judge_the_given_blocks_besides_the_ledges():
    heat = np.ones((7, 7))
    heat[1, 1] = 0.05  # on no ledge: judged only when given
    judged = np.zeros((7, 7), bool)
    judged[1, 1] = True
    none = np.zeros(TV.shape, bool)
    considered = np.zeros((7, 7), bool)
    assert ledge_regions(heat, considered, none, 0.2, 8, 2, TV, 0.5) == []
    regions = ledge_regions(heat, considered, none, 0.2, 8, 2, TV, 0.5, judged=judged)
    assert len(regions) == 1 and regions[0].min_similarity == pytest.approx(0.05)
    with pytest.raises(AnalysisError, match="block grid"):
        ledge_regions(heat, considered, none, 0.2, 8, 2, TV, 0.5, judged=np.zeros((6, 7), bool))
