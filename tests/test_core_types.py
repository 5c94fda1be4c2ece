"""The shared frames and records: TopView, CameraModel, LayerResult, Toolpath, config."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.result import BlockGrid, LayerResult, MetricScore, Region
from layerwatch.errors import ConfigError, WarpError
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.config import load_config


def test_topview_defaults_match_paper():
    tv = TopView()
    assert tv.shape == (600, 600)  # 90 mm * 6.67 px/mm
    # centre of the square lands on the image centre, +Y is up
    assert np.allclose(tv.to_px([0.0, 0.0]), [299.5, 299.5])
    up = tv.to_px([0.0, 10.0])
    assert up[1] < 299.5
    # the square's corners land on the pixel edges
    assert np.allclose(tv.to_px(tv.corners_mm[0]), [-0.5, 599.5], atol=0.2)  # 90 * 6.67 = 600.3 px, rounded to 600


def test_topview_roundtrip_and_matrix_agree():
    tv = TopView(px_per_mm=5.0, width_mm=60, height_mm=40, center_mm=(110.0, 100.0))
    pts = np.random.default_rng(0).uniform(80, 130, size=(50, 2))
    px = tv.to_px(pts)
    hom = (tv.top_from_bed @ np.c_[pts, np.ones(50)].T).T[:, :2]
    assert np.allclose(px, hom)
    assert np.allclose(tv.to_mm(px), pts)


def test_topview_rejects_bad_scale():
    with pytest.raises(ConfigError):
        TopView(px_per_mm=0)


def test_camera_model_roundtrip(tmp_path):
    cam = CameraModel(
        K=[[1000, 0, 959.5], [0, 1000, 539.5], [0, 0, 1]],
        dist=[0.1, -0.05, 0, 0, 0],
        image_size=(1920, 1080),
        rvec=[0.9, 0.1, 0.05],
        tvec=[10, 20, 300],
        markers_mm=[[-45, -45], [45, -45], [45, 45], [-45, 45]],
    )
    for name in ("cam.toml", "cam.json"):
        back = CameraModel.load(cam.save(tmp_path / name))
        assert np.allclose(back.K, cam.K) and np.allclose(back.rvec, cam.rvec)
        assert back.image_size == (1920, 1080)


def test_camera_model_scaling_keeps_projection_consistent():
    import cv2

    cam = CameraModel(
        K=[[1000, 0, 959.5], [0, 1000, 539.5], [0, 0, 1]],
        dist=np.zeros(5),
        image_size=(1920, 1080),
        rvec=[2.2, 0.0, 0.0],
        tvec=[0, 0, 300],
    )
    half = cam.scaled_to((960, 540))
    X = np.array([[10.0, 20.0, 0.0], [-30, 5, 0]])
    p_full = cv2.projectPoints(X, cam.rvec, cam.tvec, cam.K, cam.dist)[0].reshape(-1, 2)
    p_half = cv2.projectPoints(X, half.rvec, half.tvec, half.K, half.dist)[0].reshape(-1, 2)
    assert np.allclose((p_full + 0.5) / 2 - 0.5, p_half)
    with pytest.raises(WarpError):
        cam.scaled_to((1000, 1000))


def test_camera_model_load_errors(tmp_path):
    with pytest.raises(ConfigError, match="calibrate"):
        CameraModel.load(tmp_path / "missing.toml")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ConfigError, match="not valid"):
        CameraModel.load(bad)


def test_layer_result_json_roundtrip_without_nan():
    res = LayerResult(
        layer=3,
        z=1.2,
        anomaly_ratio=0.25,
        regions=[Region(12.5, (1, 2, 3, 4), (2, 3), 4, 0.4)],
        heatmap=np.array([[0.5, np.nan]], dtype=np.float32),
        timings_ms={"hog": 3.2},
    )
    text = res.to_json(include_heatmap=True)
    assert "NaN" not in text
    back = LayerResult.from_json(text)
    assert back.layer == 3 and back.regions[0].area_mm2 == 12.5
    assert back.heatmap.shape == (1, 2)


def test_layer_result_typed_fields_roundtrip_and_old_rows_with_extra():
    res = LayerResult(layer=3, z=0.9, grid=BlockGrid(cell_px=4, block_mm=1.2), shown_blocks=[1, 5],
                      per_metric={"cosine": MetricScore(0.1, 3, 0.8)}, decision="pause", decision_reason="why",
                      trigger_to_pause_ms=12.5, simulated_failures=["spaghetti"])
    back = LayerResult.from_json(res.to_json())
    assert back == res and back.region_blocks == 2
    old = {"layer": 2, "z": 0.6, "n_anomalous": 4, "extra": {  # a history row written before the typed fields
        "grid": {"cell_px": 8, "block_cells": 2, "min_region_blocks": 1, "block_mm": 2.4},
        "per_metric": {"l1": {"anomaly_ratio": 0.2, "n_anomalous": 7, "mean_similarity": 0.5}},
        "decision": "notify", "trigger_to_pause_ms": 40.0, "region_blocks": 9}}
    r = LayerResult.from_dict(old)
    assert r.grid == BlockGrid(block_mm=2.4) and r.per_metric == {"l1": MetricScore(0.2, 7, 0.5)}
    assert r.decision == "notify" and r.trigger_to_pause_ms == 40.0 and r.region_blocks == 4


def test_toolpath_from_segments_groups_layers():
    start = [[0, 0], [1, 0], [0, 0], [0, 1]]
    end = [[1, 0], [1, 1], [0, 1], [1, 1]]
    tp = Toolpath.from_segments(start, end, z=[0.2, 0.2, 0.4, 0.4])
    assert tp.n_layers == 2
    assert tp.layers[1].height == pytest.approx(0.2)
    assert tp.up_to(1) == slice(0, 4)
    assert tp.layer_index_at(0.4) == 1 and tp.layer_index_at(5.0) == -1


def test_config_defaults_and_errors(tmp_path):
    cfg = load_config()
    assert cfg.analysis.threshold == 0.7 and cfg.topview.px_per_mm == 6.67
    bad = tmp_path / "bad.toml"
    bad.write_text("[analysis]\nmetric = 'nope'\n")
    with pytest.raises(ConfigError, match="analysis.metric"):
        load_config(bad)
    bad.write_text("[analysis\n")
    with pytest.raises(ConfigError, match="TOML"):
        load_config(bad)


def test_example_config_loads():
    from layerwatch.examples import PART_CONFIG

    cfg = load_config(PART_CONFIG)
    assert cfg.topview.center_mm == (110.0, 100.0)
