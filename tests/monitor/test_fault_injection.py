"""The monitor never dies of its printer host: fault injection against the OctoPrint and Moonraker connectors.

One :class:`Monitor` per host software watches a fake host on 127.0.0.1
(:mod:`fake_host`) that is switched, one after the other, to every kind of
bad reply in :data:`fake_host.HTTP_FAULTS` (HTML with status 200, truncated
JSON, wrong types, ``NaN``, a 3 MB body, an endless chunked body, 4xx/5xx,
a hang, a reset mid-body...) and to a closed port (connection refused); in
between, malformed websocket messages are pushed through the connectors'
message handlers. After each fault the host answers properly again and a
snapshot trigger arrives: the monitor must be alive, must have seen the
host again within one poll interval (plus a little scheduling slack), and
must analyse the layer. It never pauses.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from fake_host import FINISHED, HTTP_FAULTS, FakeHost

from layerwatch.analysis.result import LayerResult
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.health import FaultSettings
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter
from layerwatch.monitor.printers.octoprint import OctoPrintPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.storage.history import History

POLL_S = 0.5
#: scheduling slack on a loaded CI machine on top of the poll interval, s
SLACK_S = 0.2

#: malformed websocket messages (OctoPrint push messages / Moonraker JSON-RPC frames)
WS_FRAMES = {
    "octoprint": ["", "not json", "[1,2]", "null", '{"current": 5}', '{"current": {"logs": 7}}',
                 '{"current": {"logs": [1, null, {"a": 1}]}}', '{"history": {"logs": "Recv: x"}}',
                 "[" * 100_000, '{"current": {"logs": ["Recv: echo:layerwatch snapshot layer=x z=nan"]}}'],
    "moonraker": ["", "garbage", "[]", "42", '{"method": "notify_gcode_response", "params": 5}',
                  '{"method": "notify_gcode_response", "params": [null, 3, {"x": 1}]}',
                  '{"method": "notify_status_update", "params": ["x"]}',
                  '{"method": "notify_status_update", "params": [{"print_stats": "printing"}]}',
                  '{"method": "notify_status_update", "params": [{"gcode_move": {"gcode_position": [1, "a", NaN]}}]}',
                  '{"method": "notify_status_update", "params": [{"virtual_sdcard": {"progress": Infinity}}]}',
                  '{"result": {"status": [1]}}', '{"result": "ok"}', "[" * 100_000],
}


class CleanPipeline:
    def __init__(self):
        self.seen: list[int] = []

    def process(self, photo, layer_index):
        self.seen.append(layer_index)
        return LayerResult(layer=layer_index, z=0.3, anomaly_ratio=0.0, printed_area_mm2=1000)


def _frame(layer):
    return np.full((48, 64, 3), layer % 256, np.uint8)


def _connector(host: FakeHost):
    if host.name == "octoprint":
        return OctoPrintPrinter(f"http://{host.hostport}", api_key="K", timeout_s=0.3, push=False)
    return MoonrakerPrinter(f"http://{host.hostport}", timeout_s=0.3, push=False)


def _push_trigger(printer, layer: int) -> None:
    """A snapshot trigger through the connector's own websocket message handler."""
    line = f"layerwatch snapshot layer={layer} z={0.2 * (layer + 1):.2f}"
    if isinstance(printer, OctoPrintPrinter):
        printer.handle_message(json.dumps({"current": {"logs": [f"Recv: echo:{line}"]}}))
    else:
        printer.handle_frame(json.dumps({"method": "notify_gcode_response", "params": [line]}))


def _until(cond, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def _run_faults(name: str, kinds: list[str], refused: bool):
    """Inject ``kinds`` (and a refused connection) into one monitored print; figures per kind."""
    host = FakeHost(name)
    printer = _connector(host)
    pipe = CleanPipeline()
    hist = History(":memory:")
    job = hist.start_job(name, "part.gcode")
    mon = Monitor(printer, SimCamera(_frame), pipe, PausePolicy(), history=hist, job_id=job, wait_for_verdict=True,
                  faults=FaultSettings(printer_grace_s=0.3))
    out: dict = {}
    t = threading.Thread(target=lambda: out.setdefault("report", mon.run(poll_s=POLL_S)), daemon=True)
    recovery: dict[str, float] = {}
    try:
        t.start()
        layer = 0
        _push_trigger(printer, layer)
        _until(lambda: pipe.seen == [0], 5, "the first layer")
        for kind in kinds + (["connection_refused"] if refused else []):
            before = mon.report.printer_faults
            if kind == "connection_refused":
                host.down()
            else:
                host.set_fault(kind)
            _until(lambda b=before: mon.report.printer_faults >= b + 2, 10, f"two failed polls with {kind}")
            assert mon.health()["printer"] is not None, kind
            for raw in WS_FRAMES[name]:  # malformed push messages while the host is down: ignored
                (printer.handle_message if name == "octoprint" else printer.handle_frame)(raw)
            back = host.up() if kind == "connection_refused" else host.set_fault(None)
            _until(lambda: mon.health()["printer"] is None, 5, f"recovery after {kind}")
            recovery[kind] = time.monotonic() - back
            assert t.is_alive(), f"the monitor died of {kind}"
            layer += 1
            _push_trigger(printer, layer)
            _until(lambda n=layer: pipe.seen[-1] == n, 5, f"layer {layer} analysed after {kind}")
        host.reply = FINISHED[name]
        t.join(10)
        assert not t.is_alive()
        return out["report"], recovery, hist.events(job), printer.status()
    finally:
        mon.stop_event.set()
        t.join(5)
        printer.close()
        host.close()
        hist.close()


def _check(name, kinds, report, recovery, events):
    n = len(kinds) + 1
    print(f"\n{name}: {n} fault kinds, recovery after the host came back: "
          f"max {max(recovery.values()) * 1000:.0f} ms, poll interval {POLL_S * 1000:.0f} ms")
    # OctoPrint shows a finished job as "Operational" (idle), Moonraker as "complete"
    assert report.outcome == ("idle" if name == "octoprint" else "done") and report.pauses == 0
    assert [r.layer for r in report.results] == list(range(n + 1))
    assert all(r.status == "ok" for r in report.results)
    slow = {k: round(v, 3) for k, v in recovery.items() if v > POLL_S + SLACK_S}
    assert not slow, f"recovered later than one poll interval: {slow}"
    kinds_seen = [e["kind"] for e in events]
    assert kinds_seen.count("printer_fault") == n and kinds_seen.count("printer_recovered") == n


FAST_KINDS = ["html_200", "truncated_json", "nan_numbers", "timeout"]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["octoprint", "moonraker"])
def test_monitor_survives_a_few_host_faults(name):
    report, recovery, events, status = _run_faults(name, FAST_KINDS, refused=True)
    _check(name, FAST_KINDS, report, recovery, events)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["octoprint", "moonraker"])
def test_monitor_survives_every_host_fault(name):
    kinds = list(HTTP_FAULTS)
    assert len(kinds) + 1 + len(WS_FRAMES[name]) >= 20
    report, recovery, events, status = _run_faults(name, kinds, refused=True)
    _check(name, kinds, report, recovery, events)
    # the grace period (0.3 s) is shorter than some outages: those were notified, once each
    assert report.alerts >= 1


@pytest.mark.parametrize("kind", list(HTTP_FAULTS))
@pytest.mark.parametrize("name", ["octoprint", "moonraker"])
def test_each_bad_reply_is_one_printer_error(name, kind):
    """Every injected reply becomes a PrinterError with one line, never another exception."""
    from layerwatch.errors import PrinterError

    host = FakeHost(name)
    printer = _connector(host)
    try:
        host.set_fault(kind)
        with pytest.raises(PrinterError) as e:
            printer.status()
        msg = str(e.value)
        assert "\n" not in msg and "Traceback" not in msg and len(msg) < 400
        host.set_fault(None)
        assert printer.status().state == "printing"
    finally:
        printer.close()
        host.close()
