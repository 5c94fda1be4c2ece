"""A farm printer's frames go through the same camera-fault gate as ``layerwatch monitor``'s.

The bed-marker check on every frame and the lag check (the photo against the previous
layer) where a result would count toward a pause: the farm's :class:`PoolPipeline` gives the
monitor what those checks read, and the records equal the single-printer monitor's.
"""

from __future__ import annotations

import time

import pytest

from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.farm.monitor import FarmMonitor, PoolPipeline
from layerwatch.farm.pool import WorkerPool
from layerwatch.farm.remote import JobContext
from layerwatch.farm.simcam import SimPrint
from layerwatch.gcode import read_toolpath
from layerwatch.monitor import camera_checks
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.base import SnapshotTrigger
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.policy import PausePolicy


def _record(res) -> dict:
    d = res.to_dict()
    d.pop("timings_ms", None)
    d.pop("photo_ms", None)  # trigger to photo, ms: a timing
    if d.get("scene"):
        d["scene"].pop("ms", None)
    return d


@pytest.mark.slow
def test_farm_monitor_runs_the_marker_and_lag_checks_of_the_single_printer_monitor(monkeypatch):
    tp, cfg = read_toolpath(PART_GCODE), resolve_config(PART_CONFIG).config
    sim = SimPrint(tp, cfg, None, 1, 1, keep=4)
    assert sim.located.markers_mm is not None and cfg.frame_quality.enabled
    lag_checked = []
    real = camera_checks.previous_layer_explains

    def spy(pipeline, photo, res, policy, *args, **kwargs):
        lag_checked.append((type(pipeline).__name__, res.layer))
        return real(pipeline, photo, res, policy, *args, **kwargs)

    monkeypatch.setattr(camera_checks, "previous_layer_explains", spy)
    # every analysed layer past the first counts here, so that the lag check runs on each
    monkeypatch.setattr(camera_checks, "counts_toward_pause", lambda res, policy: res.status == "ok" and res.layer >= 1)
    pool = WorkerPool(1)
    ctx = JobContext("gate", tp, sim.located, cfg)
    kw = dict(wait_for_verdict=True, faults=cfg.faults, frame_quality=cfg.frame_quality)
    farm = FarmMonitor(VirtualPrinter(b"G1 Z0.2\n"), SimCamera(sim.frame), PoolPipeline(pool, ctx.pipeline(), ctx),
                       PausePolicy(cfg.policy), **kw)
    single = Monitor(VirtualPrinter(b"G1 Z0.2\n"), SimCamera(sim.frame), ctx.pipeline(), PausePolicy(cfg.policy), **kw)
    try:
        assert farm.frame_checks.markers is not None and single.frame_checks.markers is not None  # the bed markers are checked
        got = {"farm": [], "single": []}
        for layer in range(3):
            for name, mon in (("farm", farm), ("single", single)):
                got[name].append(_record(mon.handle_trigger(SnapshotTrigger(layer, tp.layers[layer].z, "t",
                                                                            time.monotonic()))))
        assert [k for k, _ in lag_checked].count("PoolPipeline") == 2  # layers 1 and 2, as the monitor's
        assert [k for k, _ in lag_checked].count("LayerPipeline") == 2
        assert got["farm"] == got["single"]
    finally:
        farm.close()
        single.close()
        farm.pipeline.close()
        pool.close()
