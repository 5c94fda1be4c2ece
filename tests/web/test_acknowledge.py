"""The dashboard's acknowledge reaches the running monitor's pause policy (through the shared history)."""

from __future__ import annotations

import threading
import time

import numpy as np
from dashclient import dashboard_client

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.base import Printer, PrinterStatus, SnapshotTrigger
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.storage.history import History
from layerwatch.web.app import create_app

BOX = (100.0, 90.0, 112.0, 102.0)  # the failing region, bed mm


class HeldPrinter(Printer):
    """A connector whose triggers the test pushes (as OctoPrint's websocket would)."""

    name = "held"

    def __init__(self):
        super().__init__()
        self.state = "printing"

    def status(self):
        return PrinterStatus(self.state, "part.gcode")

    def pause(self):
        self.state = "paused"

    def resume(self):
        self.state = "printing"

    def cancel(self):
        self.state = "cancelled"

    def send_gcode(self, lines):
        pass


class RegionPipeline:
    """Stand-in pipeline: layer -> one failing region of the area the test sets (0 = clean)."""

    def __init__(self):
        self.area = {}

    def process(self, photo, layer_index):
        a = self.area.get(layer_index, 0.0)
        regions = [Region(a, BOX, (106.0, 96.0), 8, 0.3)] if a else []
        return LayerResult(layer=layer_index, z=0.2 * (layer_index + 1), anomaly_ratio=a / 400,
                           printed_area_mm2=400.0, anomalous_area_mm2=a, regions=regions)


def _until(pred, what, timeout=20.0):
    end = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < end, f"gave up waiting for {what}"
        time.sleep(0.01)


def _frame(layer):
    img = np.full((48, 64, 3), 60, np.uint8)
    img[layer % 48] = 200  # frames differ per layer
    return img


def test_dashboard_acknowledge_reaches_running_monitor_policy(tmp_path):
    db = tmp_path / "history.db"
    mon_hist = History(db)  # the monitor's connection (another process in real use)
    job = mon_hist.start_job("held", "part.gcode")
    printer, pipe = HeldPrinter(), RegionPipeline()
    mon = Monitor(printer, SimCamera(_frame), pipe, PausePolicy(), history=mon_hist, job_id=job,
                  wait_for_verdict=True)
    runner = threading.Thread(target=mon.run, kwargs={"poll_s": 0.01}, daemon=True)
    web_hist = History(db)
    client = dashboard_client(create_app(web_hist))
    runner.start()
    try:
        def layer(i, area):
            pipe.area[i] = area
            n = len(mon.report.results)
            printer._emit(SnapshotTrigger(i, 0.2 * (i + 1), "held"))
            _until(lambda: len(mon.report.results) > n, f"layer {i} analysed")
            return mon.report.decisions[-1]

        assert layer(1, 0).action == "none"
        assert layer(2, 80.0).action == "notify"
        assert layer(3, 80.0).action == "pause"  # 2 layers above 10 % in the same place
        assert printer.state == "paused" and mon.policy.halted and mon.policy.acknowledged == []

        r = client.post(f"/api/jobs/{job}/acknowledge")
        assert r.status_code == 200
        # the running monitor picks the event up from the history and acknowledges its policy
        _until(lambda: not mon.policy.halted, "the monitor to apply the dashboard's acknowledge")
        assert mon.policy.acknowledged == [(BOX, 80.0)]
        kinds = [e["kind"] for e in web_hist.events(job)]
        assert kinds[-2:] == ["acknowledge", "acknowledged"]
        assert web_hist.events(job)[-1]["data"] == {"source": "dashboard", "regions": 1}

        printer.resume()  # the operator resumes on the printer
        assert layer(4, 80.0).action == "none"  # the accepted region does not pause again
        assert layer(5, 100.0).action == "none"  # nor when it grows a little (< 1.5x)
        d = layer(6, 130.0)  # > 1.5 x 80 mm^2: it grew, pause again
        assert d.action == "pause" and "grew from 80" in d.reason
        assert printer.state == "paused"
        assert sum(e["kind"] == "acknowledged" for e in web_hist.events(job)) == 1  # applied once
    finally:
        mon.stop_event.set()
        runner.join(10)
        web_hist.close()
        mon_hist.close()


def test_without_acknowledge_the_region_stays_halted(tmp_path):
    """Control for the test above: no dashboard click, the policy stays halted while paused."""
    h = History(tmp_path / "h.db")
    job = h.start_job("held")
    printer, pipe = HeldPrinter(), RegionPipeline()
    mon = Monitor(printer, SimCamera(_frame), pipe, PausePolicy(), history=h, job_id=job, wait_for_verdict=True)
    h.add_event(job, "pause", "an unrelated event")
    for i, a in ((1, 0), (2, 80.0), (3, 80.0)):
        pipe.area[i] = a
        mon.handle_trigger(SnapshotTrigger(i, 0.2, "held"))
    assert mon.poll_acknowledgements() == 0 and mon.policy.halted
    h.add_event(job, "acknowledge", "from the dashboard")
    assert mon.poll_acknowledgements() == 1 and not mon.policy.halted
    assert mon.poll_acknowledgements() == 0  # each event applies once
    h.close()


def test_acknowledge_routes_bad_input(seeded, printer):
    h, root, ids = seeded
    c = dashboard_client(create_app(h, printers={"virtual": printer}, image_root=root))
    assert c.post("/api/jobs/999/acknowledge").status_code == 404
    r = c.post(f"/api/jobs/{ids['done']}/acknowledge")
    assert r.status_code == 409 and "has ended" in r.json()["detail"]
    # the printer button without a job id lands on that printer's running job
    assert c.post("/api/printers/virtual/acknowledge").status_code == 200
    assert h.events(ids["live"])[-1]["kind"] == "acknowledge"
