"""Hidden ledges (analysis/ledges.py): lower floors no earlier photo showed are judged by the reference's HOG."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.ledges import LEDGE_SHARE, ledge_blocks, ledge_regions
from layerwatch.errors import AnalysisError
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera

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


@pytest.mark.slow
def test_single_photo_sees_an_object_on_the_plate_beside_the_top_layer():
    """Single-photo mode (the pipeline forgets the print before the photo: bed photo and reference only): a
    screw or lump on the example part's plate while the boss above it prints lay inside the printed body,
    which the bed photo cannot judge, and was missed; the reference's HOG on the plate finds it. The clean
    photo of the same layer reports nothing there."""
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    cam = default_camera(cfg.topview.topview(), image_size=(1280, 720))
    cfg = cfg.for_camera(cam)
    tv = cfg.topview.topview()
    pipe = LayerPipeline(tp, cam, cfg, memo=2)
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
