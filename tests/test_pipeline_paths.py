"""Every driver runs the same per-layer step: the records and a% they report agree.

* the evaluation's per-layer path (:func:`layerwatch.evaluate.harness.score_layer`) and the
  monitor's (virtual printer, simulated camera, :class:`Monitor`) give identical records for
  the same photos;
* ``layerwatch compare`` on a top view / reference / footprint that ``layerwatch analyze``
  wrote reports the a% ``analyze`` reported for that layer, on a clean and on a failed layer.
"""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest

from layerwatch.analysis.settings import METRIC_NAMES
from layerwatch.cli import main
from layerwatch.evaluate.harness import THRESHOLDS, score_layer
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera

N = 6  # layers 0..5; spaghetti from layer 3
MONITOR_ONLY = ("timings_ms", "decision", "decision_reason", "photo_ms", "trigger_to_pause_ms")


@pytest.fixture(scope="module")
def job():
    cfg = resolve_config(PART_CONFIG).config  # what analyze, monitor and evaluate run by default
    tv = cfg.topview.topview()
    tp = read_toolpath(PART_GCODE)
    cam = default_camera(tv, image_size=(1280, 720))
    sim = PrintSimulator(tp, cam, tv, [Failure("spaghetti", onset=3, size_mm=16.0, seed=1)], seed=1)
    return cfg, tp, cam, [sim.frame(i) for i in range(N)]


def _record(res) -> dict:
    d = res.to_dict(include_heatmap=True)
    for key in MONITOR_ONLY:
        d.pop(key)
    if d.get("scene"):
        d["scene"].pop("ms", None)  # the scene channel's own timing
    return d


@pytest.mark.slow
def test_evaluation_and_monitor_give_identical_records(job):
    cfg, tp, cam, frames = job
    # one pipeline per print, photos in order, as the harness runs a scenario (the scene channel keeps history)
    evaluation_pipe = LayerPipeline(tp, cam, cfg, memo=tp.n_layers)
    evaluated = [score_layer(evaluation_pipe, f, i) for i, f in enumerate(frames)]
    prepared = insert_snapshots(PART_GCODE.read_bytes(), cfg.snapshot.model_copy(update={"profile": "octoprint"}),
                                cfg.printer)
    cut = prepared.find(f"layerwatch snapshot layer={N} ".encode())
    printer = VirtualPrinter(prepared[: prepared.rfind(b"\n", 0, cut)])
    report = Monitor(printer, SimCamera(lambda i: frames[i].photo), LayerPipeline(tp, cam, cfg),
                     PausePolicy(cfg.policy), wait_for_verdict=True).run(poll_s=0.01)
    monitored = {r.layer: r for r in report.results}
    assert sorted(monitored) == list(range(len(monitored))) and len(monitored) >= 4  # stops at the pause (layer 4)
    k, j = METRIC_NAMES.index(cfg.analysis.metric), int(np.argmin(abs(THRESHOLDS - cfg.analysis.threshold)))
    assert THRESHOLDS[j] == pytest.approx(cfg.analysis.threshold)
    for i, (res, scores) in enumerate(evaluated[: len(monitored)]):
        assert res.status == "ok" and scores is not None
        assert _record(res) == _record(monitored[i])
        assert np.array_equal(res.heatmap, monitored[i].heatmap) and np.array_equal(res.mask, monitored[i].mask)
        # the evaluation's sweep at the configured measure and T_S is the step's own HOG a% (eq. 5 over what
        # its anomalous blocks add to S_A: the printed share of their tiles, as recommended); the
        # changed-as-predicted channel may only add its own area to the step's
        assert cfg.analysis.anomalous_area == "printed"
        added = float(res.layer_change.added_mm2) if res.layer_change is not None else 0.0
        hog_ratio = (res.anomalous_area_mm2 - added) / res.printed_area_mm2
        tiles = res.n_anomalous * (cfg.analysis.cell_px / cfg.topview.px_per_mm) ** 2 / res.printed_area_mm2
        assert hog_ratio <= tiles + 1e-9  # a tile adds at most itself
        assert scores[0][k, j] == pytest.approx(hog_ratio, abs=1e-6)
        assert res.anomaly_ratio >= hog_ratio - 1e-9
    # the failure shows: records are not all zero (the evaluation's whole-view score: a% counts the printed
    # part of the anomalous tiles, the strands beside the layer are the scene channel's change beside the print)
    assert max(r.anomaly_ratio + r.outside_anomalous_mm2 / r.printed_area_mm2 for r, _ in evaluated[3:]) > 0.03


def _a_percent(text: str) -> float:
    return float(re.search(r"a% = ([0-9.]+)%", text).group(1))


@pytest.mark.slow
@pytest.mark.parametrize("layer", [2, 5])  # clean, spaghetti
def test_compare_reports_the_a_percent_of_analyze(job, tmp_path, capsys, layer):
    cfg, tp, cam, frames = job
    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / f"layer_{layer:04d}.png"), frames[layer].photo)
    cam.save(tmp_path / "camera.toml")
    out = tmp_path / "results"
    assert main(["analyze", str(photos / f"layer_{layer:04d}.png"), "--gcode", str(PART_GCODE),
                 "-c", str(PART_CONFIG), "--camera", str(tmp_path / "camera.toml"), "-o", str(out)]) == 0
    analysed = json.loads((out / "layers" / f"layer_{layer:04d}.json").read_text())
    assert analysed["status"] == "ok"
    capsys.readouterr()
    name = f"layer_{layer:04d}.png"
    assert main(["compare", str(out / "tops" / name), str(out / "refs" / name), "--mask", str(out / "masks" / name),
                 "-c", str(PART_CONFIG), "-o", str(tmp_path / "overlay.png")]) == 0
    compared = _a_percent(capsys.readouterr().out)
    assert compared == pytest.approx(round(100 * analysed["anomaly_ratio"], 1), abs=0.051)
    if layer == 5:  # a real a%, not 0 = 0 (the strands lie mostly beside the layer: outside_area_mm2, not a%)
        assert compared > 0.0 and analysed["n_anomalous"] >= 3
