"""End-to-end: virtual printer + simulated 1080p camera + the real LayerPipeline + PausePolicy."""

import dataclasses

import pytest

from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy


@pytest.fixture(scope="module")
def job():
    from layerwatch.examples import PART_CONFIG, PART_GCODE
    from layerwatch.gcode import read_toolpath
    from layerwatch.gcode.postprocess import insert_snapshots
    from layerwatch.geometry.pose import locate_bed
    from layerwatch.pipeline.config import recommended_config
    from layerwatch.pipeline.step import LayerPipeline
    from layerwatch.simulate import Failure, PrintSimulator, default_camera

    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    data = PART_GCODE.read_bytes()
    tp = read_toolpath(data)
    truth = default_camera(tv, image_size=(1920, 1080))
    n = 20
    clean = PrintSimulator(tp, truth, tv, [], seed=3)
    bad = PrintSimulator(tp, truth, tv, [Failure("spaghetti", onset=15, seed=1)], seed=1)
    frames = {"clean": [clean.frame(i).photo for i in range(n)], "bad": [bad.frame(i).photo for i in range(n)]}
    cam = locate_bed(dataclasses.replace(truth, rvec=None, tvec=None), frames["clean"][0], cfg.markers, tv)
    pipe = LayerPipeline(tp, cam, cfg)
    prepared = insert_snapshots(data, cfg.snapshot.model_copy(update={"profile": "octoprint"}), cfg.printer)
    # keep the first n layers' triggers only
    cut = prepared.find(f"layerwatch snapshot layer={n} ".encode())
    return cfg, pipe, prepared[: prepared.rfind(b"\n", 0, cut)], frames


@pytest.mark.slow
@pytest.mark.parametrize("wait", [True, False])
def test_failure_pauses_within_two_layers_and_clean_print_never(job, wait):
    cfg, pipe, gcode, frames = job
    vp = VirtualPrinter(gcode)
    rep = Monitor(vp, SimCamera(lambda i: frames["bad"][i]), pipe, PausePolicy(cfg.policy), wait_for_verdict=wait).run(poll_s=0.01)
    stops = [d.layer for d in rep.decisions if d.stops]
    assert stops and 15 <= stops[0] <= 16 and rep.pauses == 1
    # without waiting, the instant replay may have ended before the verdict arrives
    assert vp.status().state == "paused" if wait else vp.status().state in ("paused", "finished")
    print(f"\n1080p, wait_for_verdict={wait}: trigger -> pause request {rep.latencies_ms[0]:.0f} ms "
          "(includes queueing behind the previous layer when not waiting; the virtual printer has no print time)")
    vp2 = VirtualPrinter(gcode)
    rep2 = Monitor(vp2, SimCamera(lambda i: frames["clean"][i]), pipe, PausePolicy(cfg.policy), wait_for_verdict=wait).run(poll_s=0.01)
    assert rep2.pauses == 0 and len(rep2.results) == 20 and vp2.status().state == "finished"


@pytest.mark.slow
def test_pause_alert_carries_the_overlay_of_the_failing_layer(job):
    cfg, pipe, gcode, frames = job

    class Recorder:
        def __init__(self):
            self.sent = []

        def notify(self, title, message, *, level="warning", image=None, data=None, force=False):
            self.sent.append((level, image, data))
            return True

    rec = Recorder()
    vp = VirtualPrinter(gcode)
    rep = Monitor(vp, SimCamera(lambda i: frames["bad"][i]), pipe, PausePolicy(cfg.policy), notifier=rec,
                  wait_for_verdict=True).run(poll_s=0.01)
    assert rep.pauses == 1
    critical = [(img, data) for level, img, data in rec.sent if level == "critical"]
    assert critical, rec.sent
    img, data = critical[0]
    assert img is not None and img.shape == (*pipe.topview.shape, 3) and img.dtype.name == "uint8"
    assert 15 <= data["layer"] <= 16
    assert img.std() > 10  # a picture, not a blank
