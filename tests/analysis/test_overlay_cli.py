"""Overlay/heatmap pictures and the `layerwatch compare` command."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from analysis_scenes import TOPVIEW, part_scene

from layerwatch.analysis.block_masks import block_tiles
from layerwatch.analysis.overlay import heatmap_image, overlay_image, write_overlay
from layerwatch.analysis.scoring import analyze_layer
from layerwatch.cli import main
from layerwatch.errors import AnalysisError


@pytest.fixture(scope="module")
def spaghetti():
    ref, photo, foot = part_scene(0, "spaghetti")
    return ref, photo, foot, analyze_layer(photo, ref, foot, TOPVIEW)


def test_block_tiles_cover_block_centres():
    vals = np.arange(6, dtype=np.int32).reshape(2, 3)
    img = block_tiles(vals, (24, 32), cell_px=8, block_cells=2, fill=-1)
    # block (i, j) spans rows [8i, 8i+16); its tile is the central 8 px: rows [8i+4, 8i+12)
    assert img[4, 4] == 0 and img[11, 11] == 0 and img[12, 12] == 4 and img[4, 20] == 2
    assert img[3, 3] == -1 and img[20, 30] == -1


def test_overlay_marks_regions_and_footprint(spaghetti, tmp_path):
    ref, photo, foot, res = spaghetti
    rgb = overlay_image(photo, res, TOPVIEW, foot)
    assert rgb.shape == (*TOPVIEW.shape, 3) and rgb.dtype == np.uint8
    magenta = (rgb[..., 0] > 200) & (rgb[..., 1] < 80) & (rgb[..., 2] > 200)
    cyan = (rgb[..., 0] < 80) & (rgb[..., 1] > 180) & (rgb[..., 2] > 200)
    assert magenta.sum() > 50 and cyan.sum() > 50
    ys, xs = np.nonzero(magenta)
    u = TOPVIEW.to_px(np.array(res.regions[0].centroid_mm))[0]
    assert abs(np.median(xs) - u) < 40  # outline drawn around the spaghetti region
    path = write_overlay(tmp_path / "sub" / "o.png", photo, res, TOPVIEW, foot)
    back = cv2.imread(str(path))[..., ::-1]
    np.testing.assert_array_equal(back, rgb)


def test_heatmap_image(spaghetti):
    res = spaghetti[3]
    img = heatmap_image(res, scale=4)
    assert img.shape == (res.heatmap.shape[0] * 4, res.heatmap.shape[1] * 4, 3)
    i, j = np.unravel_index(np.argmin(np.where(res.mask, res.heatmap, 2)), res.heatmap.shape)
    r, g, _ = img[i * 4, j * 4]
    assert r > g  # low similarity is red


def test_overlay_bad_input(spaghetti):
    ref, photo, foot, res = spaghetti
    with pytest.raises(AnalysisError):
        overlay_image(photo[:-1], res, TOPVIEW)
    with pytest.raises(AnalysisError):
        overlay_image(photo, res, TOPVIEW, foot[:-1])


def test_compare_cli_writes_overlay_and_json(spaghetti, tmp_path, capsys):
    ref, photo, foot, res = spaghetti
    for name, img in (("photo.png", photo), ("ref.png", ref), ("mask.png", foot.astype(np.uint8) * 255)):
        cv2.imwrite(str(tmp_path / name), img)
    out = tmp_path / "ov.png"
    rc = main([
        "compare", str(tmp_path / "photo.png"), str(tmp_path / "ref.png"), "--mask", str(tmp_path / "mask.png"),
        "--px-per-mm", "6.67", "-o", str(out), "--all-metrics", "--json", str(tmp_path / "r.json"),
        "--paper-settings",  # the fixture is scored with the paper's settings
    ])
    text = capsys.readouterr().out
    assert rc == 0 and out.is_file()
    assert f"a% = {100 * res.anomaly_ratio:.1f}%" in text and "kendall" in text
    data = json.loads((tmp_path / "r.json").read_text())
    assert data["anomaly_ratio"] == pytest.approx(res.anomaly_ratio)
    assert len(data["regions"]) == len(res.regions)


def test_compare_cli_errors_are_one_line(tmp_path, capsys):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((64, 64), np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((64, 80), np.uint8))
    (tmp_path / "junk.png").write_bytes(b"not an image")
    for args in (
        ["compare", str(tmp_path / "a.png"), str(tmp_path / "missing.png")],
        ["compare", str(tmp_path / "a.png"), str(tmp_path / "b.png")],
        ["compare", str(tmp_path / "a.png"), str(tmp_path / "junk.png")],
        ["compare", str(tmp_path / "a.png"), str(tmp_path / "a.png"), "--metric", "nope"],
    ):
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and "\n" not in err


def test_anomalous_blocks_follow_min_region_filter():
    from layerwatch.analysis.overlay import anomalous_blocks
    from layerwatch.analysis.settings import AnalysisSettings

    ref, photo, foot = part_scene(0, "blob")  # one big region and small specks
    counts = []
    for k in (1, 4):
        res = analyze_layer(photo, ref, foot, TOPVIEW, AnalysisSettings(min_region_blocks=k))
        anom = anomalous_blocks(res)
        assert anom.sum() == res.n_anomalous == sum(g.n_blocks for g in res.regions)
        assert all(g.n_blocks >= k for g in res.regions)
        counts.append(len(res.regions))
    assert counts[1] == 1 < counts[0]


def test_overlay_draws_a_regions_own_shape(spaghetti):
    """A region's ``outline_mm`` (what the evaluation's IoU scores) is drawn in white, where it lies."""
    import dataclasses

    ref, photo, foot, res = spaghetti
    cx, cy = res.regions[0].centroid_mm
    square = ((cx - 6.0, cy - 6.0), (cx + 6.0, cy - 6.0), (cx + 6.0, cy + 6.0), (cx - 6.0, cy + 6.0))
    shaped = dataclasses.replace(res, regions=[dataclasses.replace(res.regions[0], outline_mm=(square,)), *res.regions[1:]])
    plain, drawn = overlay_image(photo, res, TOPVIEW, foot), overlay_image(photo, shaped, TOPVIEW, foot)
    new = np.any(plain != drawn, axis=2) & np.all(drawn > 230, axis=2)
    assert new.sum() > 40
    ys, xs = np.nonzero(new)
    (u0, v0), (u1, v1) = TOPVIEW.to_px(np.array([square[0], square[2]]))
    lo_u, hi_u, lo_v, hi_v = min(u0, u1) - 3, max(u0, u1) + 3, min(v0, v1) - 3, max(v0, v1) + 3
    assert ((xs >= lo_u) & (xs <= hi_u) & (ys >= lo_v) & (ys <= hi_v)).all()
