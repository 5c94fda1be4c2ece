"""Job start through the monitor: a leftover object holds the (virtual) printer before layer 1, with its picture."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.examples import PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.config import recommended_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import PrintSimulator, default_camera
from layerwatch.simulate.bed_scene import Leftover, start_photo


class Alerts:
    def __init__(self):
        self.sent = []

    def notify(self, title, body, **kw):
        self.sent.append((title, body, kw))


@pytest.fixture(scope="module")
def job():
    cfg = recommended_config()
    data = PART_GCODE.read_bytes()
    tp = read_toolpath(data)
    x0, y0, x1, y1 = tp.bounds
    cfg = cfg.model_copy(update={"topview": cfg.topview.model_copy(update={
        "center_mm": ((x0 + x1) / 2, (y0 + y1) / 2), "width_mm": 90.0, "height_mm": 90.0})})
    tv = cfg.topview.topview()
    cam = default_camera(tv, image_size=(640, 360))
    sim = PrintSimulator(tp, cam, tv, seed=2)
    prepared = insert_snapshots(data, cfg.snapshot.model_copy(update={"profile": "octoprint"}), cfg.printer)
    return cfg, tp, cam, sim, prepared


@pytest.mark.parametrize("leftover", [True, False])
def test_job_start_holds_on_a_leftover_and_watches_a_clean_bed(job, leftover):
    cfg, tp, cam, sim, prepared = job
    c = cfg.topview.center_mm
    objs = (Leftover("screw", (c[0] - 12, c[1] + 8), 14.0, 1.0),) if leftover else ()
    seen = []

    def frame(i):
        if i < 0:
            return start_photo(sim, objs, index=5)
        seen.append(i)
        return sim.frame(min(i, 2)).photo

    vp = VirtualPrinter(prepared)
    alerts = Alerts()
    pipe = LayerPipeline(tp, cam, cfg, bed_photo=sim.bed_photo())
    mon = Monitor(vp, SimCamera(frame), pipe, PausePolicy(cfg.policy), notifier=alerts, wait_for_verdict=True)
    if not leftover:
        first = mon.check_bed()
        assert first is not None and first.layer == -1
        assert first.failed_check == "" and vp.status().state != "paused" and not alerts.sent
        return
    rep = mon.run(poll_s=0.001)
    first = rep.results[0]
    assert vp.pause_count == 1 and vp.status().state == "paused" and not seen  # held before layer 1
    assert rep.decisions[0].stops and rep.decisions[0].layer == -1 and "bed is not empty" in rep.decisions[0].reason
    title, body, kw = alerts.sent[0]
    assert kw["level"] == "critical" and isinstance(kw["image"], np.ndarray) and kw["image"].ndim == 3
    assert first.check_regions and first.check_regions[0].kind == "foreign_body"
