import numpy as np

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.errors import CameraError
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy, PolicySettings


def _gcode(n):
    return "\n".join(
        f"G1 Z{0.3 * (i + 1):.2f}\n@layerwatch snapshot layer={i} z={0.3 * (i + 1):.3f}\n"
        f"M118 E1 layerwatch snapshot layer={i} z={0.3 * (i + 1):.3f}" for i in range(n)
    ).encode()


class StandInPipeline:
    """Stand-in for LayerPipeline: reads the 'failure' from the photo's brightness."""

    def __init__(self):
        self.seen = []

    def process(self, photo, layer_index):
        self.seen.append(layer_index)
        bad = float(photo[0, 0, 0]) / 255.0
        regions = [Region(200 * bad + 1, (90, 90, 110, 110), (100, 100), 4, 0.4)] if bad else []
        return LayerResult(layer=layer_index, z=0.3 * (layer_index + 1), anomaly_ratio=bad,
                           printed_area_mm2=1000, anomalous_area_mm2=1000 * bad, regions=regions)


def _frame(onset):
    def f(layer):
        img = np.zeros((64, 64, 3), np.uint8)
        img[0, 0] = 80 if onset is not None and layer >= onset else 0
        img[1:, :, 1] = layer  # frames differ per layer
        return img
    return f


def test_clean_virtual_print_no_pause():
    vp = VirtualPrinter(_gcode(30))
    pipe = StandInPipeline()
    rep = Monitor(vp, SimCamera(_frame(None)), pipe, PausePolicy()).run(poll_s=0.001)
    assert pipe.seen == list(range(30)) and rep.pauses == 0 and rep.outcome == "done"
    assert vp.status().state == "finished"


def test_failure_pauses_within_two_layers_and_latency_recorded():
    vp = VirtualPrinter(_gcode(30))
    mon = Monitor(vp, SimCamera(_frame(10)), StandInPipeline(), PausePolicy(PolicySettings()), wait_for_verdict=True)
    mon.stop_event.set  # noqa: B018
    # step until paused (the demo loop waits for the operator while paused)
    while vp.status().state == "printing":
        t = vp.step_to_next_trigger()
        if t is None:
            break
        mon.handle_trigger(t)
    assert vp.status().state == "paused" and vp.pause_count == 1
    paused_at = mon.report.results[-1]
    assert 10 <= paused_at.layer <= 11
    lat = mon.report.latencies_ms
    assert len(lat) == 1 and lat[0] >= 0
    print(f"\ntrigger -> pause request latency (stand-in pipeline): {lat[0]:.1f} ms")
    # operator resumes; the same (not growing) failure does not pause again
    mon.acknowledge()
    vp.resume()
    while (t := vp.step_to_next_trigger()) is not None:
        mon.handle_trigger(t)
    assert vp.pause_count == 1 and vp.status().state == "finished"


class BrokenCamera:
    def grab(self):
        raise CameraError("camera http://x returned a web page, not an image")


def test_camera_errors_alert_but_never_pause():
    vp = VirtualPrinter(_gcode(8))
    sent = []

    class N:
        def notify(self, title, message, **kw):
            sent.append(message)
            return True

    rep = Monitor(vp, BrokenCamera(), StandInPipeline(), notifier=N()).run(poll_s=0.001)
    # one alert for the episode, after 3 bad frames in a row (FaultSettings.camera_alert_after), not one per layer
    assert rep.pauses == 0 and vp.pause_count == 0 and rep.alerts == 1 and rep.camera_faults == 8
    assert all(r.status == "camera_fault" for r in rep.results) and "web page" in sent[0]
    assert "3 unusable frames in a row" in sent[0]


class ErrorPipeline:
    """Every layer fails to analyse (the policy alerts on each, never pauses)."""

    def process(self, photo, layer_index):
        return LayerResult(layer=layer_index, z=0.3, status="error", message="warp failed: web page")


def test_slow_notifier_does_not_hold_up_analysis_and_every_alert_is_sent():
    import threading

    vp = VirtualPrinter(_gcode(6))
    release, sent = threading.Event(), []

    class SlowNotifier:  # a target that hangs until the print is over
        def notify(self, title, message, **kw):
            release.wait(timeout=30)
            sent.append(message)
            return True

    mon = Monitor(vp, SimCamera(_frame(None)), ErrorPipeline(), notifier=SlowNotifier())
    done = threading.Event()
    runner = threading.Thread(target=lambda: (mon.run(poll_s=0.001), done.set()))
    runner.start()
    # all six layers are handled while the first alert is still stuck in the notifier
    for _ in range(500):
        if len(mon.report.results) == 6:
            break
        threading.Event().wait(0.01)
    assert len(mon.report.results) == 6 and sent == []
    assert not done.is_set()  # run() waits for the queued alerts: none is lost
    release.set()
    runner.join(timeout=30)
    assert done.is_set() and len(sent) == 6 and mon.report.alerts == 6
    assert all("web page" in m for m in sent)


def test_background_analysis_keeps_order():
    vp = VirtualPrinter(_gcode(12))
    rep = Monitor(vp, SimCamera(_frame(None)), StandInPipeline()).run(poll_s=0.001)
    assert [r.layer for r in rep.results] == list(range(12))


class _ScriptedPrinter:
    """Minimal non-virtual Printer stand-in: scripted states, one trigger per poll."""

    def __init__(self, states, triggers):
        self.states, self.triggers, self.paused = list(states), list(triggers), 0

    def poll_triggers(self):
        return [self.triggers.pop(0)] if self.triggers else []

    def status(self):
        from layerwatch.monitor.printers.base import PrinterStatus

        return PrinterStatus(self.states.pop(0) if len(self.states) > 1 else self.states[0])

    def pause(self):
        self.paused += 1


def test_operator_resume_acknowledges():
    from layerwatch.monitor.printers.base import SnapshotTrigger

    trig = [SnapshotTrigger(i, 0.3 * i) for i in range(1, 4)]
    p = _ScriptedPrinter(["printing", "printing", "paused", "printing", "printing", "finished"], trig)
    mon = Monitor(p, SimCamera(_frame(1)), StandInPipeline(), wait_for_verdict=True)
    mon.run(poll_s=0.001)
    assert p.paused == 1 and not mon.policy.halted


class _EndsWhileBusyPrinter:
    """A host that prints on while the monitor takes a photo: the last layers' triggers and the end of the
    print come in together (the state is read after they arrived, before they were polled)."""

    def __init__(self, n):
        from layerwatch.monitor.printers.base import SnapshotTrigger

        self.pending = [SnapshotTrigger(0, 0.3)]
        self.rest = [SnapshotTrigger(i, 0.3 * (i + 1)) for i in range(1, n)]
        self.polls = 0

    def poll_triggers(self):
        out, self.pending = self.pending, []
        return out

    def status(self):
        from layerwatch.monitor.printers.base import PrinterStatus

        self.polls += 1
        if self.polls == 1:  # the first photo took long: every other layer printed meanwhile, and the file ended
            self.pending += self.rest
        return PrinterStatus("finished")


def test_triggers_that_came_with_the_end_of_the_print_are_judged():
    """A run that ends on 'finished' still judges the triggers pending when it read that state (they were dropped)."""
    pipe = StandInPipeline()
    rep = Monitor(_EndsWhileBusyPrinter(5), SimCamera(_frame(None)), pipe).run(poll_s=0.001)
    assert [r.layer for r in rep.results] == list(range(5)) and pipe.seen == list(range(5))
