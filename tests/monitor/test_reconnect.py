"""The monitor survives a printer that goes away and comes back.

1. A connector that fails N status polls in a row (fast, always runs): capped
   exponential backoff, one alert per outage, a reconnect log, no pause.
2. A real Moonraker stopped and restarted in the middle of a real Klippy print
   (needs .ci/install-moonraker): the monitor alerts, keeps retrying, sees the
   layers again after Moonraker is back, and never pauses the print.
"""

import logging
import threading

import httpx
import numpy as np
import pytest
from moonraker_stack import MoonrakerStack, klipper_gcode, require_installed, until

from layerwatch.analysis.result import LayerResult
from layerwatch.errors import PrinterError
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.health import FaultSettings
from layerwatch.monitor.printers.base import Printer, PrinterStatus, SnapshotTrigger
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy

pytestmark = pytest.mark.xdist_group("servers")


class CleanPipeline:
    def __init__(self):
        self.seen = []

    def process(self, photo, layer_index):
        self.seen.append(layer_index)
        return LayerResult(layer=layer_index, z=0.3, anomaly_ratio=0.0, printed_area_mm2=1000)


def _frame(layer):
    return np.full((48, 64, 3), layer % 256, np.uint8)


class FlakyPrinter(Printer):
    """Each status() call takes the next step: a state, or an exception to raise."""

    name = "flaky"

    def __init__(self, steps):
        super().__init__()
        self.steps, self.i, self.pauses = steps, 0, 0

    def poll_triggers(self):
        step = self.steps[min(self.i, len(self.steps) - 1)]
        return [SnapshotTrigger(step[1], 0.3, self.name)] if isinstance(step, tuple) and step[1] is not None else []

    def status(self):
        step = self.steps[min(self.i, len(self.steps) - 1)]
        self.i += 1
        if isinstance(step, Exception):
            raise step
        return PrinterStatus(step[0])

    def pause(self):
        self.pauses += 1

    resume = cancel = pause

    def send_gcode(self, lines):
        pass


def _retry_waits(caplog):
    return [r.retry_s for r in caplog.records if getattr(r, "event", "") == "printer_unreachable"]


def test_outage_backoff_is_exponential_capped_and_resets(caplog):
    down = PrinterError("Moonraker at http://127.0.0.1:9 unreachable (ConnectError); check host, port and that it runs.")
    steps = ([("printing", 0)] + [down] * 6 + [("printing", 1), ("printing", 2)] + [down] * 2
             + [("printing", 3), ("finished", None)])
    printer = FlakyPrinter(steps)
    mon = Monitor(printer, SimCamera(_frame), CleanPipeline(), PausePolicy(), wait_for_verdict=True,
                  initial_backoff_s=0.01, max_backoff_s=0.04, faults=FaultSettings(printer_grace_s=0))
    with caplog.at_level(logging.DEBUG, logger="layerwatch.monitor"):
        rep = mon.run(poll_s=0)
    # doubling from 0.01 s, capped at 0.04 s; back to 0.01 s after the printer answered
    assert _retry_waits(caplog) == [0.01, 0.02, 0.04, 0.04, 0.04, 0.04, 0.01, 0.02]
    assert rep.alerts == 4  # per outage: one when the grace period (0 s) is over, one at recovery; not one per retry
    assert sum("printer fault" in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING) == 2
    reconnects = [r for r in caplog.records if getattr(r, "event", "") == "printer_reconnected"]
    assert [r.failed_polls for r in reconnects] == [6, 2]
    assert printer.pauses == 0 and rep.pauses == 0  # an unreachable printer never pauses
    assert [r.layer for r in rep.results] == [0, 1, 2, 3] and rep.outcome == "done"


@pytest.mark.slow
@pytest.mark.moonraker
def test_moonraker_restart_mid_print(tmp_path, caplog):
    require_installed()
    stack = MoonrakerStack(tmp_path)
    printer = None
    mon = None
    t = None
    try:
        stack.start()
        printer = MoonrakerPrinter(stack.url, timeout_s=2)
        assert printer.wait_connected(15)
        pipe = CleanPipeline()
        mon = Monitor(printer, SimCamera(_frame), pipe, PausePolicy(), initial_backoff_s=0.1, max_backoff_s=0.4,
                      faults=FaultSettings(printer_grace_s=0))
        out = {}
        t = threading.Thread(target=lambda: out.setdefault("report", mon.run(poll_s=0.05)), daemon=True)
        with caplog.at_level(logging.DEBUG, logger="layerwatch"):
            stack.upload_and_print("lw_restart.gcode", klipper_gcode(n_layers=80, layer_s=0.2))
            t.start()
            until(lambda: len(pipe.seen) >= 2, 20, "two analysed layers")
            stack.stop_moonraker()  # Klippy keeps printing; layerwatch loses its printer host
            until(lambda: len(_retry_waits(caplog)) >= 4, 20, "four failed polls")
            stack.start_moonraker()
            stack.wait_ready()
            until(lambda: any(getattr(r, "event", "") == "printer_reconnected" for r in caplog.records), 20,
                  "the monitor to reconnect")
            n = len(pipe.seen)
            until(lambda: len(pipe.seen) >= n + 2, 20, "layers analysed after Moonraker came back")
            httpx.post(stack.url + "/printer/print/cancel", timeout=10).raise_for_status()
            t.join(20)
        waits = _retry_waits(caplog)
        assert waits[:4] == [0.1, 0.2, 0.4, 0.4] and max(waits) == 0.4
        assert mon.report.alerts >= 1 and mon.report.pauses == 0
        assert not t.is_alive() and out["report"].outcome == "cancelled"
        # layers printed while Moonraker was down were never seen; the ones after are, in order
        assert pipe.seen == sorted(set(pipe.seen))
    except BaseException:
        print(stack.log_tail())
        raise
    finally:
        if mon is not None:
            mon.stop_event.set()
        if t is not None and t.is_alive():
            t.join(10)
        if printer is not None:
            printer.close()
        stack.stop()
