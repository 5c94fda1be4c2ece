"""MoonrakerPrinter against a REAL Moonraker 0.11 and a REAL Klippy (no hardware).

See moonraker_stack.py for how Klippy runs without a printer. Nothing here fakes
Moonraker's HTTP or websocket API; the only test-side helper inside Klippy is the
real-time layer wait (debug-output mode would otherwise print instantly).
"""

import threading

import httpx
import numpy as np
import pytest
from moonraker_stack import MoonrakerStack, klipper_gcode, require_installed, running, until

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.errors import PrinterError
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy

pytestmark = [pytest.mark.moonraker, pytest.mark.xdist_group("servers")]


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    require_installed()
    s = MoonrakerStack(tmp_path_factory.mktemp("moonraker"))
    with running(s):
        yield s


@pytest.mark.slow
def test_real_moonraker_triggers_status_pause_resume_cancel(stack):
    info = MoonrakerPrinter(stack.url, push=False)
    try:
        si = info.server_info()
        assert si["klippy_state"] == "ready" and si["moonraker_version"].startswith("0.11")
        assert info.status().state == "idle"  # print_stats "standby"
    finally:
        info.close()

    printer = MoonrakerPrinter(f"moonraker://127.0.0.1:{stack.port}")
    try:
        assert printer.wait_connected(15), "websocket subscription never answered"
        stack.upload_and_print("lw_part.gcode", klipper_gcode(n_layers=40, layer_s=0.25))
        seen = []
        until(lambda: seen.extend(printer.poll_triggers()) or len(seen) >= 2, 30, "two layer triggers")
        assert [(t.layer, t.z) for t in seen[:2]] == [(0, 0.3), (1, 0.6)]
        st = until(lambda: (s := printer.status()).state == "printing" and s, 10, "state printing")
        assert st.file == "lw_part.gcode" and st.layer is not None and st.layer >= 1
        assert st.z is not None and st.z >= 0.6 and 0 < st.progress < 1

        printer.pause()
        until(lambda: printer.status().state == "paused", 15, "print_stats paused")
        # Klippy itself, queried through Moonraker without layerwatch: paused, SD card stopped
        q = stack.query("pause_resume", "print_stats", "virtual_sdcard")
        assert q["pause_resume"]["is_paused"] is True and q["print_stats"]["state"] == "paused"
        assert q["virtual_sdcard"]["is_active"] is False
        layer_at_pause = printer.status().layer

        printer.resume()
        until(lambda: printer.status().state == "printing", 15, "printing after resume")
        until(lambda: seen.extend(printer.poll_triggers()) or seen[-1].layer > layer_at_pause + 1, 15,
              "triggers after resume")
        # every layer reported once, in order, none lost across pause/resume
        assert [t.layer for t in seen] == list(range(seen[-1].layer + 1))

        printer.send_gcode('RESPOND MSG="layerwatch snapshot layer=999 z=99.000"')
        until(lambda: any(t.layer == 999 for t in printer.poll_triggers()), 10, "trigger from send_gcode")

        printer.cancel()
        until(lambda: printer.status().state == "cancelled", 15, "print_stats cancelled")
    finally:
        printer.close()


@pytest.mark.slow
def test_klippy_restart_is_a_clear_error_then_triggers_flow_again(stack):
    printer = MoonrakerPrinter(stack.url)
    try:
        assert printer.wait_connected(15)
        stack.stop_klippy()
        err = until(lambda: _error_of(printer.status), 10, "an error while Klippy is down")
        assert "Klippy Host not connected" in str(err) and "traceback" not in str(err).lower()
        stack.start_klippy()
        stack.wait_ready()
        # Moonraker re-subscribes for its clients when Klippy comes back: the same websocket delivers
        until(lambda: printer.send_gcode('RESPOND MSG="layerwatch snapshot layer=7 z=2.100"') or
              any(t.layer == 7 for t in printer.poll_triggers()), 15, "trigger after Klippy restart")
        assert printer.status().state == "idle"
    finally:
        printer.close()


def _error_of(fn):
    try:
        fn()
    except PrinterError as exc:
        return exc
    return None


@pytest.mark.slow
def test_klippy_shutdown_during_print_is_error_not_pause(stack):
    """After M112 print_stats still says "paused"; the connector must report Klippy's shutdown."""
    printer = MoonrakerPrinter(stack.url)
    try:
        assert printer.wait_connected(15)
        stack.upload_and_print("lw_shutdown.gcode", klipper_gcode(n_layers=40, layer_s=0.25))
        until(lambda: printer.poll_triggers(), 15, "a layer trigger")
        httpx.post(stack.url + "/printer/emergency_stop", timeout=5).raise_for_status()
        until(lambda: stack.query("webhooks")["webhooks"]["state"] == "shutdown", 10, "Klippy shutdown")
        assert stack.query("print_stats")["print_stats"]["state"] in ("paused", "printing", "error")
        assert printer.status().state == "error"
        httpx.post(stack.url + "/printer/firmware_restart", timeout=10).raise_for_status()
        stack.wait_ready()
        until(lambda: printer.status().state == "idle", 15, "idle after FIRMWARE_RESTART")
    finally:
        printer.close()


class _FlagPipeline:
    """Stand-in analysis (the real pipeline is tested elsewhere): a fixed failing region from ``onset`` on."""

    def __init__(self, onset):
        self.onset, self.seen = onset, []

    def process(self, photo, layer_index):
        self.seen.append(layer_index)
        bad = layer_index >= self.onset
        regions = [Region(60.0, (90, 90, 110, 110), (100, 100), 4, 0.4)] if bad else []
        return LayerResult(layer=layer_index, z=0.3 * (layer_index + 1), anomaly_ratio=0.3 if bad else 0.0,
                           printed_area_mm2=1000, anomalous_area_mm2=300 if bad else 0, regions=regions)


def _frame(layer):
    img = np.zeros((48, 64, 3), np.uint8)
    img[..., 1] = layer % 256
    return img


@pytest.mark.slow
def test_monitor_pauses_a_real_moonraker_print_and_acknowledges_the_operator_resume(stack):
    printer = MoonrakerPrinter(stack.url)
    pipe = _FlagPipeline(onset=3)
    mon = Monitor(printer, SimCamera(_frame), pipe, PausePolicy())
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("report", mon.run(poll_s=0.05)), daemon=True)
    try:
        assert printer.wait_connected(15)
        stack.upload_and_print("lw_monitor.gcode", klipper_gcode(n_layers=40, layer_s=0.25))
        t.start()
        until(lambda: stack.query("print_stats")["print_stats"]["state"] == "paused", 20,
              "Klippy paused by the monitor")
        # Klippy can report "paused" before the monitor's pause request has returned and been counted
        until(lambda: mon.report.pauses >= 1, 10, "the monitor to count its pause")
        assert mon.report.pauses == 1 and mon.policy.halted
        paused_on = next(r for r in mon.report.results if r.decision == "pause")
        assert 3 <= paused_on.layer <= 4  # k=2 consecutive layers from the onset at layer 3
        print(f"\nMoonraker: trigger -> pause request {paused_on.trigger_to_pause_ms} ms (stand-in analysis)")
        # the operator resumes on the printer's own UI (not through layerwatch)
        httpx.post(stack.url + "/printer/print/resume", timeout=10).raise_for_status()
        until(lambda: not mon.policy.halted, 15, "the monitor to acknowledge the operator's resume")
        n = len(pipe.seen)
        until(lambda: len(pipe.seen) >= n + 2, 15, "layers analysed after the resume")
        assert mon.report.pauses == 1  # the acknowledged region does not pause again
        httpx.post(stack.url + "/printer/print/cancel", timeout=10).raise_for_status()
        t.join(20)
        assert not t.is_alive() and out["report"].outcome == "cancelled"
        assert pipe.seen == list(range(len(pipe.seen)))
    finally:
        mon.stop_event.set()
        if t.is_alive():
            t.join(10)
        printer.close()
