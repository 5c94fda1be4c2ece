"""Offline analysis of a photo series: layer assignment, bad/missing photos, resume."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from layerwatch.evaluate.offline import assign_layers, run_offline
from layerwatch.pipeline.config import JobConfig
from layerwatch.simulate import Failure, default_camera, save_frame, simulate_print
from layerwatch.simulate.parts import box_part


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    root = tmp_path_factory.mktemp("series")
    cfg = JobConfig(analysis={"threshold": 0.4, "footprint_margin_mm": 0.0})
    tv = cfg.topview.topview()
    cam = default_camera(tv, image_size=(960, 540))
    tp = box_part(size_mm=24.0, height_mm=2.4, layer_h=0.3)
    fails = [Failure("layer_shift", onset=4, size_mm=4.0, seed=2)]
    for fr in simulate_print(tp, cam, tv, fails, seed=1):
        save_frame(fr, root)
    cam.save(root / "camera.toml")
    return root, tp, cam, cfg


def test_assign_layers_by_number_and_order():
    m, problems = assign_layers(["b/layer_0002.png", "a/layer_0000.png", "x_7.png", "dup_2.png"], 5)
    assert m[0].name == "layer_0000.png" and m[2].name == "layer_0002.png"
    assert len(problems) == 2 and any("not in the G-code" in p for p in problems)
    m, problems = assign_layers(["first.png", "second.png"], 5)
    assert [p.name for p in m.values()] == ["first.png", "second.png"] and not problems


def test_assign_layers_skips_simulator_truth_masks():
    names = ["layer_0001.png", "layer_0001_truth.png", "layer_0001_area.png", "layer_0002.png"]
    m, problems = assign_layers(names, 5)
    assert {i: p.name for i, p in m.items()} == {1: "layer_0001.png", 2: "layer_0002.png"}
    assert len(problems) == 1 and "ground-truth" in problems[0]


def test_run_offline_reports_bad_and_missing_and_resumes(series, tmp_path):
    root, tp, cam, cfg = series
    photos = sorted(root.glob("layer_????.png"))
    photos = [p for p in photos if p.stem != "layer_0003"]  # a missing layer
    bad = tmp_path / "layer_0005.png"
    bad.write_bytes(b"not a png")
    photos = [p for p in photos if p.stem != "layer_0005"] + [bad]
    gray = tmp_path / "layer_0006.png"
    cv2.imwrite(str(gray), np.zeros((100, 100), np.uint8))  # wrong aspect ratio: warp fails
    photos = [p for p in photos if p.stem != "layer_0006"] + [gray]
    out = tmp_path / "res"
    run = run_offline(tp, cam, cfg, photos, out)
    assert run.missing == [3]
    assert run.results[5].status == "error" and "readable" in run.results[5].message
    assert run.results[6].status == "error"
    assert all(run.results[i].status == "ok" for i in (0, 1, 2, 4, 7))
    assert run.paused_at is not None and run.paused_at >= 4
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_error"] == 2 and summary["paused_at_layer"] == run.paused_at
    assert (out / "overlays" / "layer_0004.png").is_file() and (out / "stack.png").is_file()
    # resume: finished layers are not redone, failed ones are retried
    before = (out / "layers" / "layer_0001.json").stat().st_mtime_ns
    again = run_offline(tp, cam, cfg, photos, out)
    assert again.reused == 5
    assert (out / "layers" / "layer_0001.json").stat().st_mtime_ns == before
    assert again.results[1].anomaly_ratio == pytest.approx(run.results[1].anomaly_ratio)


def test_cli_analyze_and_simulate(tmp_path, capsys):
    from layerwatch.cli import main

    sim = tmp_path / "sim"
    assert main(["simulate", "--layers", "3", "--width", "640", "-o", str(sim), "-f", "spaghetti@1"]) == 0
    assert (sim / "layer_0002_truth.png").is_file() and (sim / "camera.toml").is_file()
    from layerwatch.examples import PART_GCODE

    photos = [str(p) for p in sorted(sim.glob("layer_????.png"))]
    rc = main(["analyze", "--gcode", str(PART_GCODE), "--camera", str(sim / "camera.toml"),
               "-o", str(tmp_path / "res"), *photos])
    assert rc == 0
    assert "3 of 3 layers analysed" in capsys.readouterr().out
    assert main(["analyze", "--gcode", str(PART_GCODE), "--camera", str(tmp_path / "nope.toml"), photos[0]]) == 2
