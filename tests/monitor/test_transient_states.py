"""Transient job states (pausing / resuming / cancelling) in the Monitor loop.

A scripted connector plays back the states a host reports, one per monitor poll;
the monitor must not take "pausing" for paused nor "pausing -> printing" for an
operator's resume, must acknowledge "paused -> resuming -> printing" once, and
must keep watching while a job is "cancelling".
"""

import numpy as np

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.base import Printer, PrinterStatus, SnapshotTrigger
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy


class ScriptedPrinter(Printer):
    """Step ``i`` of ``script``: ``(state, trigger_layer or None)``; one step per ``status()`` call."""

    name = "scripted"

    def __init__(self, script):
        super().__init__()
        self.script, self.i = script, 0
        self.calls: list[str] = []

    def _step(self):
        return self.script[min(self.i, len(self.script) - 1)]

    def poll_triggers(self):
        layer = self._step()[1] if self.i < len(self.script) else None
        return [] if layer is None else [SnapshotTrigger(layer, 0.3 * (layer + 1), self.name)]

    def status(self):
        state = self._step()[0]
        self.i += 1
        return PrinterStatus(state)

    def pause(self):
        self.calls.append("pause")

    def resume(self):
        self.calls.append("resume")

    def cancel(self):
        self.calls.append("cancel")

    def send_gcode(self, lines):
        self.calls.append("gcode")


class FailFrom:
    def __init__(self, onset):
        self.onset = onset

    def process(self, photo, layer_index):
        bad = layer_index >= self.onset
        return LayerResult(layer=layer_index, z=0.3, anomaly_ratio=0.3 if bad else 0.0, printed_area_mm2=1000,
                           anomalous_area_mm2=300 if bad else 0,
                           regions=[Region(60.0, (90, 90, 110, 110), (100, 100), 4, 0.4)] if bad else [])


def _run(script):
    printer = ScriptedPrinter(script)
    mon = Monitor(printer, SimCamera(lambda layer: np.full((48, 64, 3), layer, np.uint8)), FailFrom(0), PausePolicy(),
                  wait_for_verdict=True)
    rep = mon.run(poll_s=0)
    return printer, mon, rep


# layer 0 is not judged (first layer); layers 1 and 2 fail (k=2) -> the monitor pauses at layer 2
FAILING = [("printing", 0), ("printing", 1), ("printing", 2)]


def test_pausing_then_printing_is_not_an_operator_resume():
    printer, mon, rep = _run(FAILING + [("pausing", None), ("pausing", None), ("printing", None),
                                           ("printing", 3), ("cancelled", None)])
    assert printer.calls == ["pause"] and rep.pauses == 1
    assert [r.layer for r in rep.results if r.decision == "pause"] == [2]
    assert mon.policy.halted  # no acknowledge: the pause never completed, nobody resumed
    assert rep.outcome == "cancelled"


def test_paused_resuming_printing_is_acknowledged_once():
    printer, mon, rep = _run(FAILING + [("pausing", None), ("paused", None), ("paused", None),
                                           ("resuming", None), ("resuming", None), ("printing", None),
                                           ("printing", 3), ("printing", 4), ("finished", None)])
    assert not mon.policy.halted  # acknowledged at resuming -> printing (the paused state was kept)
    assert rep.pauses == 1 and printer.calls == ["pause"]  # the acknowledged region does not pause again
    assert rep.outcome == "done"


def test_cancelling_keeps_the_monitor_running_until_cancelled():
    script = [("printing", 0), ("cancelling", None), ("cancelling", None), ("cancelling", None),
              ("cancelled", None)]
    printer, mon, rep = _run(script)
    assert rep.pauses == 0
    assert printer.i >= len(script)  # it polled through every "cancelling" instead of stopping there
    assert rep.outcome == "cancelled"


def test_transient_flag():
    assert PrinterStatus("pausing").transient and PrinterStatus("cancelling").transient
    assert not PrinterStatus("paused").transient and not PrinterStatus("printing").transient
