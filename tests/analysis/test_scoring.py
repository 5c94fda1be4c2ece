"""analyze_layer: heatmap, eq. (5) ratio, regions in bed mm, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from analysis_scenes import TOPVIEW, part_scene

from layerwatch.analysis.result import LayerResult
from layerwatch.analysis.scoring import analyze_layer, block_geometry, grey_u8, reference_hog
from layerwatch.analysis.settings import METRIC_NAMES, AnalysisSettings
from layerwatch.errors import AnalysisError
from layerwatch.geometry.topview import TopView


def test_clean_layer_scores_low_and_defects_are_found_where_they_are():
    ref, photo, foot = part_scene(0)
    clean = analyze_layer(photo, ref, foot, TOPVIEW, layer=3, z=0.9)
    assert clean.ok and clean.layer == 3 and clean.z == 0.9
    assert clean.anomaly_ratio < 0.03
    assert clean.heatmap.shape == (TOPVIEW.shape[0] // 8 - 1, TOPVIEW.shape[1] // 8 - 1)
    assert clean.heatmap.dtype == np.float32 and np.isfinite(clean.heatmap).all()

    ref, photo, foot = part_scene(0, "blob")
    blob = analyze_layer(photo, ref, foot, TOPVIEW)
    big = blob.regions[0]
    assert blob.anomaly_ratio > clean.anomaly_ratio + 0.02
    assert big.centroid_mm == pytest.approx((104.0, 103.0), abs=1.5)  # bed mm, where it was drawn
    x0, y0, x1, y1 = big.bbox_mm
    assert x0 < 104 < x1 and y0 < 103 < y1 and x1 > x0 and y1 > y0
    assert big.outside_fraction < 0.1 and big.min_similarity <= big.mean_similarity < 0.7

    ref, photo, foot = part_scene(0, "spaghetti")
    spag = analyze_layer(photo, ref, foot, TOPVIEW)
    top = spag.regions[0]
    assert top.outside_fraction > 0.9  # beside the part, where the reference is empty
    assert top.centroid_mm[0] > 120 and spag.outside_area_mm2 >= top.area_mm2 * 0.9
    assert spag.anomaly_ratio > 0.15

    ref, photo, foot = part_scene(0, "missing")
    miss = analyze_layer(photo, ref, foot, TOPVIEW)
    assert miss.regions[0].outside_fraction < 0.3 and miss.anomaly_ratio > 0.2


def test_eq5_areas_are_consistent():
    ref, photo, foot = part_scene(1, "blob")
    r = analyze_layer(photo, ref, foot, TOPVIEW)
    tile = (8 / TOPVIEW.px_per_mm) ** 2
    assert r.printed_area_mm2 == pytest.approx(foot.sum() / TOPVIEW.px_per_mm**2)
    assert r.anomalous_area_mm2 == pytest.approx(r.n_anomalous * tile)
    assert r.anomaly_ratio == pytest.approx(r.anomalous_area_mm2 / r.printed_area_mm2)
    assert sum(g.area_mm2 for g in r.regions) == pytest.approx(r.anomalous_area_mm2)
    assert r.n_anomalous == int((r.mask & (r.heatmap < r.threshold)).sum())
    assert [g.area_mm2 for g in r.regions] == sorted((g.area_mm2 for g in r.regions), reverse=True)


def test_margin_decides_whether_material_beside_the_part_counts():
    ref, photo, foot = part_scene(0, "spaghetti")
    near = analyze_layer(photo, ref, foot, TOPVIEW, AnalysisSettings(footprint_margin_mm=5.0))
    none = analyze_layer(photo, ref, foot, TOPVIEW, AnalysisSettings(footprint_margin_mm=0.0))
    assert near.outside_area_mm2 > 50 > none.outside_area_mm2
    assert none.n_blocks < near.n_blocks


def test_valid_mask_excludes_blocks_the_camera_did_not_see():
    ref, photo, foot = part_scene(0, "spaghetti")
    valid = np.ones(foot.shape, bool)
    valid[:, TOPVIEW.shape[1] // 2 + 60 :] = False  # right side unseen (spaghetti there)
    r = analyze_layer(photo, ref, foot, TOPVIEW, valid=valid)
    assert all(g.centroid_mm[0] < 122 for g in r.regions)
    assert r.printed_area_mm2 == pytest.approx((foot & valid).sum() / TOPVIEW.px_per_mm**2)


def test_block_geometry_and_smaller_cells():
    g8 = block_geometry(8, 2, 6.67)
    g4 = block_geometry(4, 2, 6.67)
    assert g8["block_mm"] == pytest.approx(2.4, abs=0.01)  # 16 px / 6.67 px/mm
    assert g8["paper_block_mm"] == pytest.approx(4.8, abs=0.01)  # the paper's figure (32 px)
    assert block_geometry(16, 2, 6.67)["block_mm"] == pytest.approx(4.8, abs=0.01)
    assert g4["block_mm"] == pytest.approx(g8["block_mm"] / 2)
    assert g4["paper_block_mm"] == pytest.approx(g8["paper_block_mm"] / 2)
    # and the analysis grid follows: twice the blocks per axis, a quarter of the tile area
    ref, photo, foot = part_scene(0, "blob")
    r8 = analyze_layer(photo, ref, foot, TOPVIEW, AnalysisSettings(cell_px=8))
    r4 = analyze_layer(photo, ref, foot, TOPVIEW, AnalysisSettings(cell_px=4))
    assert r4.grid.block_mm == pytest.approx(r8.grid.block_mm / 2)
    assert r4.heatmap.shape[0] == TOPVIEW.shape[0] // 4 - 1
    assert r4.regions and r4.regions[0].centroid_mm == pytest.approx((104.0, 103.0), abs=1.5)


@pytest.mark.parametrize("metric", METRIC_NAMES)
def test_every_metric_runs_and_json_round_trips(metric):
    ref, photo, foot = part_scene(2, "blob")
    r = analyze_layer(photo, ref, foot, TOPVIEW, AnalysisSettings(metric=metric))
    assert r.metric == metric and np.isfinite(r.heatmap).all()
    assert 0 <= r.heatmap.min() and r.heatmap.max() <= 1
    back = LayerResult.from_json(r.to_json(include_heatmap=True))
    np.testing.assert_allclose(back.heatmap, r.heatmap, atol=1e-4)
    np.testing.assert_array_equal(back.mask, r.mask)
    assert back.regions == r.regions
    json.loads(r.to_json())  # without heatmap too


def test_blank_images_give_defined_results():
    foot = np.zeros(TOPVIEW.shape, bool)
    foot[100:200, 100:200] = True
    for value in (0, 255):
        img = np.full(TOPVIEW.shape, value, np.uint8)
        r = analyze_layer(img, img, foot, TOPVIEW)
        assert r.ok and r.anomaly_ratio == 0.0 and np.all(r.heatmap == 1.0)
    black, ref, _ = np.zeros(TOPVIEW.shape, np.uint8), *part_scene(0)[:2]
    r = analyze_layer(black, ref, foot, TOPVIEW)  # camera saw nothing but the part should be there
    assert r.anomaly_ratio > 0.9 and np.isfinite(r.heatmap).all()
    empty = analyze_layer(ref, ref, np.zeros(TOPVIEW.shape, bool), TOPVIEW)
    assert empty.status == "skipped" and empty.anomaly_ratio == 0.0


def test_float_and_colour_inputs():
    ref, photo, foot = part_scene(0, "blob")
    r8 = analyze_layer(photo, ref, foot, TOPVIEW)
    rf = analyze_layer(photo / 255.0, ref / 255.0, foot, TOPVIEW)
    np.testing.assert_allclose(rf.heatmap, r8.heatmap, atol=1e-4)
    rc = analyze_layer(np.dstack([photo] * 3), np.dstack([ref] * 3), foot, TOPVIEW)
    np.testing.assert_array_equal(rc.heatmap, r8.heatmap)


def test_bad_input_raises_one_line_analysis_errors():
    ref, photo, foot = part_scene(0)
    nan = photo.astype(np.float32) / 255
    nan[5, 5] = np.nan
    cases = [
        (photo[:-8], ref, foot, TOPVIEW),  # sizes differ
        (photo, ref.astype(np.float32), foot, TOPVIEW),  # dtypes differ
        (nan, ref.astype(np.float32) / 255, foot, TOPVIEW),  # NaN
        (photo, ref, foot[:-1], TOPVIEW),  # mask shape
        (photo, ref, foot, TopView(px_per_mm=5.0, width_mm=45.0, height_mm=45.0)),  # wrong top view
        (photo.astype(np.int64), ref.astype(np.int64), foot, TOPVIEW),  # dtype not supported
    ]
    for args in cases:
        with pytest.raises(AnalysisError) as info:
            analyze_layer(*args)
        assert "\n" not in str(info.value)
    with pytest.raises(AnalysisError):
        analyze_layer(photo, ref, foot, TOPVIEW, valid=foot[:, :-1])
    small = TopView(px_per_mm=1.0, width_mm=10.0, height_mm=10.0)
    with pytest.raises(AnalysisError):
        analyze_layer(photo[:10, :10], ref[:10, :10], foot[:10, :10], small)


def test_real_photo_pair_smoke(shared_data):
    """Two consecutive real camera frames: runs, finite, some but not all blocks differ."""
    import cv2

    paths = [shared_data / "photos" / f"caxton_nozzle_sample{n}.jpg" for n in ("0021", "0022")]
    if not all(p.is_file() for p in paths):
        pytest.skip("caxton photos not in shared data")
    a, b = (cv2.imread(str(p))[60:660, 340:940] for p in paths)  # colour, BGR
    tv = TopView(px_per_mm=6.67, width_mm=600 / 6.67, height_mm=600 / 6.67)
    r = analyze_layer(a, b, np.ones((600, 600), bool), tv, all_metrics=True)
    assert r.ok and np.isfinite(r.heatmap).all() and 0.0 < r.anomaly_ratio < 0.6
    assert r.regions and set(r.per_metric) == set(METRIC_NAMES)
    same = analyze_layer(a, a, np.ones((600, 600), bool), tv)
    assert same.anomaly_ratio == 0.0 and np.all(same.heatmap == 1.0)


def test_grow_regions_is_hysteresis():
    from layerwatch.analysis.scoring import grow_regions

    loose = np.zeros((10, 10), bool)
    loose[1:4, 1:5] = True   # component with a seed
    loose[7:9, 7:9] = True   # component without one
    seeds = np.zeros_like(loose)
    seeds[2, 2] = True
    seeds[5, 0] = True       # a seed outside the loose mask stays
    out = grow_regions(seeds, loose)
    assert out[1:4, 1:5].all() and out[5, 0]
    assert not out[7:9, 7:9].any()
    assert out.sum() == 12 + 1


def test_grown_regions_extend_what_is_shown_not_the_ratio():
    from layerwatch.analysis.overlay import anomalous_blocks

    ref, photo, foot = part_scene(0, "blob")
    plain = analyze_layer(photo, ref, foot, TOPVIEW, AnalysisSettings(threshold=0.5))
    grown = analyze_layer(photo, ref, foot, TOPVIEW, AnalysisSettings(threshold=0.5, grow_threshold=0.3))
    assert grown.anomaly_ratio == plain.anomaly_ratio  # a% counts blocks below T_S only
    assert grown.regions == plain.regions  # so do the regions the pause policy reads
    assert grown.region_blocks > grown.n_anomalous
    drawn = anomalous_blocks(grown)
    assert drawn.sum() == grown.region_blocks
    assert (drawn >= anomalous_blocks(plain)).all()


def test_presmooth_removes_pixel_noise_before_the_hog():
    ref, photo, foot = part_scene(0)
    rng = np.random.default_rng(3)
    noisy = np.clip(photo.astype(np.float32) + rng.normal(0, 10, photo.shape), 0, 255).astype(np.uint8)
    raw = analyze_layer(noisy, ref, foot, TOPVIEW, AnalysisSettings(footprint_margin_mm=0))
    smooth = analyze_layer(noisy, ref, foot, TOPVIEW, AnalysisSettings(footprint_margin_mm=0, presmooth_px=1.25))
    assert smooth.similarity_mean > raw.similarity_mean + 0.02
    assert smooth.anomaly_ratio < raw.anomaly_ratio


def test_flat_tolerance_forgives_faint_reference_texture_the_photo_lacks_but_nothing_else():
    from layerwatch.analysis.scoring import block_hogs

    flat = np.full((48, 96), 120, np.uint8)
    faint, strong = flat.copy(), flat.copy()
    stripes = ((np.arange(48)[:, None] // 2) % 2 == 0).repeat(48, 1)  # horizontal lines, 4 px period
    faint[:, :48][stripes] += 6  # mean |gradient| 5.85 grey levels: above 5, below 1.5 x 5
    strong[:, :48][stripes] += 60
    left = (slice(None), slice(0, 4))  # blocks lying wholly on the left half
    for tol, forgiven in ((1.0, False), (1.5, True)):
        st = AnalysisSettings(min_gradient=5.0, flat_tolerance=tol)
        h_photo, h_ref = block_hogs(flat, faint, st)  # the renderer's faint lines, a plain photo
        assert (not h_ref[left].any()) == forgiven
        assert not h_photo[:, -4:].any() and not h_ref[:, -4:].any()  # flat in both: always featureless
        h_photo, _ = block_hogs(faint, flat, st)  # faint texture in the photo only: always compared
        assert h_photo[left].any()
        _, h_ref = block_hogs(flat, strong, st)  # strong reference texture missing from the photo
        assert h_ref[left].any()


def test_grey_u8_of_a_colour_image_is_the_floor_of_the_channel_mean_for_every_colour():
    v = np.arange(256, dtype=np.uint8)
    b, g, r = (a.reshape(4096, 4096) for a in np.meshgrid(v, v, v, indexing="ij"))
    img = np.stack([b, g, r], -1)
    want = ((b.astype(np.uint16) + g + r) // 3).astype(np.uint8)
    assert np.array_equal(grey_u8(img), want)
    bgra = np.dstack([img[:64, :64], np.full((64, 64), 7, np.uint8)])
    assert np.array_equal(grey_u8(bgra), want[:64, :64])  # alpha ignored


def test_a_reference_hog_computed_ahead_gives_the_same_result_and_is_not_changed():
    st = AnalysisSettings(presmooth_px=1.25, min_gradient=2.0)
    for kind in (None, "blob"):
        ref, photo, foot = part_scene(0, kind) if kind else part_scene(0)
        ahead = reference_hog(ref, st)
        before = ahead[0].copy()
        assert ahead[0].ndim == 3 and ahead[0].shape[2] == st.bins  # cell histograms, not blocks
        a = analyze_layer(photo, ref, foot, TOPVIEW, st)
        b = analyze_layer(photo, ref, foot, TOPVIEW, st, ref_hog=ahead)
        assert np.array_equal(a.heatmap, b.heatmap) and a.anomaly_ratio == b.anomaly_ratio
        assert np.array_equal(ahead[0], before) and not ahead[0].flags.writeable


def _wall_scene(texture_rows: slice) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A wall's top (grey 200, rows 85-96: it starts 5 px into a cell) on a flat grey-60 surround; the
    photo is the reference with strong vertical stripes in ``texture_rows`` (columns 64-159)."""
    h, w = TOPVIEW.shape
    foot = np.zeros((h, w), bool)
    foot[85:97, 40:200] = True
    ref = np.full((h, w), 60, np.uint8)
    ref[foot] = 200
    photo = ref.copy()
    stripes = ((np.arange(w)[None, :] // 3) % 2 == 0) & (np.arange(w)[None, :] >= 64) & (np.arange(w)[None, :] < 160)
    band = np.zeros((h, w), bool)
    band[texture_rows] = True
    photo[band & stripes] = 150
    return ref, photo, foot


def test_printed_area_counts_what_lies_beside_a_wall_as_outside_not_as_a_percent():
    """The cause of the window part's clean alarms (issue 18): a camera at 45 degrees sees past a wall's edge
    (the floor of a hollow part through its opening, the wall's own face), and a block is considered when
    one of its cells touches the footprint, although its tile (the cell at its centre) lies beside it.
    Texture there that the reference lacks made whole tiles of S_A; with ``anomalous_area = "printed"`` a
    block adds only the printed part of its tile, and the rest is the area beside the layer."""
    tile = (8 / TOPVIEW.px_per_mm) ** 2
    tiles, printed = AnalysisSettings(footprint_margin_mm=0.0), AnalysisSettings(footprint_margin_mm=0.0,
                                                                                anomalous_area="printed")
    ref, photo, foot = _wall_scene(slice(72, 80))  # the cell just beside the wall (blocks of row 9 touch it)
    a = analyze_layer(photo, ref, foot, TOPVIEW, tiles)
    b = analyze_layer(photo, ref, foot, TOPVIEW, printed)
    assert a.n_anomalous == b.n_anomalous >= 8  # the same blocks fail
    assert a.anomaly_ratio > 0.025  # above the recommended pause ratio: an alarm on a clean layer
    assert b.anomaly_ratio == 0.0 and b.anomalous_area_mm2 == 0.0
    assert b.outside_area_mm2 == pytest.approx(a.outside_area_mm2) == pytest.approx(a.n_anomalous * tile)
    # texture on the wall's top itself is a failure of the printed layer: counted by its printed share
    ref, photo, foot = _wall_scene(slice(88, 96))
    a = analyze_layer(photo, ref, foot, TOPVIEW, tiles)
    b = analyze_layer(photo, ref, foot, TOPVIEW, printed)
    assert b.n_anomalous == a.n_anomalous >= 8
    assert b.anomaly_ratio > 0.5 * a.anomaly_ratio > 0.0
    assert b.anomalous_area_mm2 + b.outside_area_mm2 == pytest.approx(a.anomalous_area_mm2)
    assert b.anomaly_ratio == pytest.approx(b.anomalous_area_mm2 / b.printed_area_mm2)
    # what S_A leaves out of the anomalous tiles is kept: S_A + uncounted is the tiles' area in both modes
    assert a.uncounted_mm2 == 0.0 and b.uncounted_mm2 > 0.0
    assert b.anomalous_area_mm2 + b.uncounted_mm2 == pytest.approx(a.anomalous_area_mm2) == pytest.approx(
        a.n_anomalous * tile)


def test_anomalous_area_is_a_job_setting_printed_recommended_and_the_papers_tiles_kept():
    """``printed`` is recommended since the series scene channel judges the part's lower floors with a
    clipped red channel (session 11, docs/evaluation/single_photo.md); the paper's whole tiles stay the
    default of ``--paper-settings`` and a job may choose them."""
    from layerwatch.pipeline.config import resolve_config

    assert resolve_config(None).config.analysis.anomalous_area == "printed"
    assert resolve_config(None, recommended=False).config.analysis.anomalous_area == "tiles"
    chosen = resolve_config(None, flags={"analysis": {"anomalous_area": "tiles"}})
    assert chosen.config.analysis.anomalous_area == "tiles"
    assert chosen.config.analysis.metric == "jaccard"  # the rest of the recommendation still applies


def test_printed_weight_counts_the_parts_own_gaps_whole_and_nothing_beside_it():
    """Sparse infill (lines 3 mm apart) is the part's inside: its cells show lower layers through the part
    and count whole, as in the paper; a hollow part's 12 mm opening and the bed around it count nothing."""
    from layerwatch.analysis.scoring import PART_GAP_MM, printed_weight, tile_share

    px = TOPVIEW.px_per_mm
    foot = np.zeros(TOPVIEW.shape, bool)
    r0, r1, c0, c1 = (int(round(v * px)) for v in (5, 35, 5, 40))
    foot[r0:r1, c0:c0 + 3] = foot[r0:r1, c1 - 3:c1] = foot[r0:r0 + 3, c0:c1] = foot[r1 - 3:r1, c0:c1] = True
    for x in np.arange(8, 22, 3.0):  # sparse infill in the left half: 0.45 mm lines every 3 mm
        c = int(round(x * px))
        foot[r0:r1, c:c + 3] = True
    foot[r0:r1, int(round(22 * px)):int(round(23.8 * px))] = True  # a wall; right of it a 16 mm opening
    share = tile_share(foot, (TOPVIEW.shape[0] // 8 - 1, TOPVIEW.shape[1] // 8 - 1), 8, 2)
    w = printed_weight(share, 8 / px)
    tile = lambda x, y: (int((y * px - 4) // 8), int((x * px - 4) // 8))  # noqa: E731  block whose tile holds (x, y) mm
    assert w[tile(15.5, 20)] == 1.0 and share[tile(15.5, 20)] < 0.5  # a sparse-infill cell: whole
    assert w[tile(31, 20)] == 0.0  # the middle of the opening: beside the part
    assert w[tile(43, 20)] == 0.0  # the bed
    assert 0.0 < w[tile(23.9, 20)] < 1.0  # the wall's edge: its printed share
    assert PART_GAP_MM < 12.0


def test_area_weight_modes():
    from layerwatch.analysis.scoring import area_weight

    share = np.zeros((12, 12))
    share[5, 2:10] = 0.4  # a thin wall's edge tiles
    share[0, 0] = 1.0
    tiles, part, printed = (area_weight(share, 1.2, m) for m in ("tiles", "part", "printed"))
    assert (tiles == 1).all()
    assert (part[5, 2:10] == 1).all() and part[8, 8] == 0 and part[0, 0] == 1  # wholly beside the part: nothing
    assert np.allclose(printed[5, 2:10], 0.4) and printed[8, 8] == 0
