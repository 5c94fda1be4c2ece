"""The evaluation by mode: per-photo scores (kind of the covering region, IoU, displacement error) and their summary."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.evaluate.harness import LayerRecord
from layerwatch.evaluate.modes import MISSED, ModeScore, marked_area, mode_score, summarize_modes
from layerwatch.evaluate.report import _modes, type_label
from layerwatch.geometry.topview import TopView

TV = TopView(px_per_mm=4.0, width_mm=40.0, height_mm=40.0, center_mm=(0.0, 0.0))


def _region(x0, y0, x1, y1, kind="", conf=0.0, disp=None) -> Region:
    return Region(area_mm2=(x1 - x0) * (y1 - y0), bbox_mm=(x0, y0, x1, y1), centroid_mm=((x0 + x1) / 2, (y0 + y1) / 2),
                  n_blocks=1, mean_similarity=0.1, kind=kind, kind_confidence=conf, displacement_mm=disp)


def _truth(x0, y0, x1, y1) -> np.ndarray:
    m = np.zeros(TV.shape, bool)
    (u0, v0), (u1, v1) = np.round(TV.to_px(np.array([[x0, y1], [x1, y0]], float))).astype(int)
    m[v0:v1, u0:u1] = True
    return m


def test_the_region_covering_the_failure_names_its_kind_and_displacement_error():
    res = LayerResult(layer=3, z=0.6, anomaly_ratio=0.1, printed_area_mm2=200.0, outside_anomalous_mm2=20.0,
                      regions=[_region(-10, -10, -8, -8, "spaghetti", 0.7)],
                      outside_regions=[_region(2, 2, 8, 8, "layer_shift", 0.9, (2.2, 0.1))])
    m = mode_score(res, _truth(3, 3, 9, 9), TV, np.array([2.0, 0.0]))
    assert m.kind == "layer_shift" and m.confidence == pytest.approx(0.9)
    assert m.displacement_error_mm == pytest.approx(np.hypot(0.2, 0.1))
    assert m.score == pytest.approx(0.1 + 20.0 / 200.0)
    assert 0.3 < m.iou < 1.0  # the 6 x 6 mm box against the 6 x 6 mm truth shifted by 1 mm
    # nothing covers a failure elsewhere: missed; a clean photo has no kind and no IoU
    assert mode_score(res, _truth(-18, 12, -14, 16), TV).kind == MISSED
    clean = mode_score(res, None, TV)
    assert clean.kind == "" and clean.iou is None
    # a refused photo is no score
    bad = mode_score(LayerResult(layer=3, z=0.6, status="error"), _truth(3, 3, 9, 9), TV)
    assert bad.status == "error" and np.isnan(bad.score)


def test_marked_area_is_the_anomalous_tiles_and_the_outside_boxes():
    res = LayerResult(layer=0, z=0.2, outside_regions=[_region(0, 0, 4, 4)])
    area = marked_area(res, TV)
    assert area.sum() == pytest.approx(_truth(0, 0, 4, 4).sum(), rel=0.25)


def test_a_moved_parts_outline_replaces_its_box_in_the_marked_area():
    """A moved part marks its outline (where it is and where it should be), not the box of its blocks."""
    band = ((2.0, 2.0), (4.0, 2.0), (4.0, 10.0), (2.0, 10.0))
    moved = _region(0, 0, 12, 12, "layer_shift", 0.9, (2.0, 0.0))
    moved.outline_mm = (band,)
    res = LayerResult(layer=0, z=0.2, outside_regions=[moved, _region(-10, -10, -6, -6)])
    area = marked_area(res, TV)
    assert area.sum() == pytest.approx(_truth(2, 2, 4, 10).sum() + _truth(-10, -10, -6, -6).sum(), rel=0.25)
    assert not area[_truth(6, 6, 12, 12)].any()  # the rest of the moved region's box is not marked
    m = mode_score(LayerResult(layer=0, z=0.2, regions=[moved]), _truth(2, 2, 4, 10), TV, np.array([2.0, 0.0]))
    assert m.iou > 0.75 and m.kind == "layer_shift"


def test_a_moved_parts_outline_also_stands_for_the_tiles_grown_from_its_blocks():
    """Tiles connected to a moved region's box (its hysteresis growth) give way to the outline; others stay."""
    from layerwatch.analysis.result import BlockGrid

    # TV is 160 x 160 px; 8 px cells, 2-cell blocks: a 19 x 19 grid of blocks, block (i, j) owns px 8i+4 .. 8i+12
    heat = np.ones((19, 19), np.float32)
    heat[4:6, 4:12] = 0.0  # a strip of failing blocks, rows 36..52 px, cols 36..100 px
    heat[15, 15] = 0.0  # an isolated failing block elsewhere
    band = ((8.0, -10.0), (10.0, -10.0), (10.0, -6.0), (8.0, -6.0))
    moved = _region(-12, 8, -8, 11, "detachment", 0.9, (1.0, 0.0))  # its box covers the strip's left end only
    moved.outline_mm = (band,)
    res = LayerResult(layer=0, z=0.2, threshold=0.5, heatmap=heat, regions=[moved],
                      grid=BlockGrid(cell_px=8, block_cells=2))
    area = marked_area(res, TV)
    strip = np.zeros(TV.shape, bool)
    strip[36:52, 36:100] = True
    assert not (area & strip).any()  # the whole strip, not only the part in the box, is the moved part
    assert area[124:132, 124:132].all()  # the isolated block is still marked
    assert area[_truth(8, -10, 10, -6)].mean() > 0.9  # and the outline
    moved.kind = "spaghetti"  # an outlined region that is not a moved part gives way to its box only
    assert (marked_area(res, TV) & strip).sum() > 0


def _rec(kind, since, score, typed="", err=None, iou=None, size=8.0, mode="series"):
    r = LayerRecord("s", kind, 1, size if kind != "clean" else 0.0, np.zeros((1, 1)), since_onset=since)
    r.modes[mode] = ModeScore(score, iou=iou, kind=typed, displacement_error_mm=err)
    return r


def test_summarize_modes_counts_confusion_auroc_and_displacement():
    recs = [_rec("clean", -1, s) for s in (0.0, 0.01, 0.02)]
    recs += [_rec("layer_shift", 0, 0.5, "layer_shift", 0.3, 0.6), _rec("layer_shift", 1, 0.6, "detachment", 0.9, 0.4),
             _rec("layer_shift", 2, 0.005, MISSED, None, 0.0),
             _rec("spaghetti", 0, 0.3, "spaghetti", None, 0.7, size=3.0)]
    f = summarize_modes(recs, 5.0)
    assert set(f) == {"series"}  # only the modes every record has
    s = f["series"]
    assert s["n_clean"] == 3
    assert s["confusion"]["layer_shift"]["layer_shift"] == 1 and s["confusion"]["layer_shift"]["detachment"] == 1
    assert s["confusion"]["layer_shift"][MISSED] == 1 and s["confusion"]["spaghetti"]["spaghetti"] == 1
    assert s["displacement"]["layer_shift"] == [0.3, 0.9]
    assert s["auroc"]["layer_shift"] == pytest.approx((3 + 3 + 1) / 9)  # 0.005 beats one clean photo of three
    assert s["auroc"]["spaghetti"] == 1.0
    assert {d: n for d, n, _ in s["since"]["layer_shift"]} == {0: 1, 1: 1, 2: 1}
    assert s["iou"]["layer_shift"] == (pytest.approx(1.0 / 3), 3) and s["iou"]["spaghetti"][1] == 0  # 3 mm: not scored
    # a 2 mm shift moves the whole layer's outline: it counts in the IoU whatever its displacement
    small = summarize_modes([*recs[:3], _rec("layer_shift", 0, 0.5, "layer_shift", 0.3, 0.6, size=2.0)], 5.0)
    assert small["series"]["iou"]["layer_shift"] == (pytest.approx(0.6), 1)


def test_report_section_shows_both_modes_and_the_targets():
    recs = []
    for mode in ("single", "series"):
        for r in [_rec("clean", -1, 0.0, mode=mode), _rec("layer_shift", 0, 0.5, "layer_shift", 0.2, 0.6, mode=mode)]:
            recs.append(r)
    # one record per photo carries both modes
    both = [recs[0], recs[1]]
    both[0].modes.update(recs[2].modes)
    both[1].modes.update(recs[3].modes)

    class S:  # the part of Summary the section reads
        modes = summarize_modes(both, 5.0)

    run = {"layers": 3000, "pauses": 0, "layer_alarms": 2, "ratio_layers": 5, "parts": {"part.gcode": {
           "prints": 1, "layers": 33, "layer_alarms": 0, "ratio_layers": 1, "policy_alarms": 0, "pauses": 0,
           "outside_layers": 0}}}
    text = "\n".join(_modes(S, run, {}))
    assert "### single mode" in text and "### series mode" in text
    assert "| AUROC single mode: foreign body, spaghetti, detachment, layer shift | >= 0.97 | layer_shift 1.000 | yes |" in text
    assert "| false pauses in >= 3000 clean layers (series mode) | 0 | 0 in 3000 layers | yes |" in text
    assert "| single-layer alarms (a% above the pause ratio and the minimum area) | <= 1 / 1000 | 0.67 / 1000" in text
    assert "| part.gcode | 1 | 33 | 0 | 1 |" in text and "5 with a% alone above the ratio" in text


def test_a_thin_wall_defect_on_a_part_without_thin_walls_is_labelled_a_wall_gap():
    assert type_label("thin_wall", {"thin_walls": False}) == "thin_wall (wall gap: no thin wall in this part)"
    assert type_label("thin_wall", {"thin_walls": True}) == "thin_wall"
    assert type_label("thin_wall", {}) == "thin_wall"  # a report from an older run says nothing of it
    assert type_label("detachment", {"thin_walls": False}) == "detachment"
