"""Moonraker connector on recorded JSON-RPC frames (no Moonraker/Klippy runs here).

The frames follow Moonraker's documented websocket notifications
(notify_gcode_response, notify_status_update, printer.objects.subscribe reply).
"""

import json

import pytest

from layerwatch.errors import PrinterError
from layerwatch.monitor.printers.moonraker import SUBSCRIBE, MoonrakerPrinter

FRAMES = [
    {"jsonrpc": "2.0", "result": {"eventtime": 10.0, "status": {
        "print_stats": {"state": "printing", "filename": "part_lw.gcode"},
        "gcode_move": {"gcode_position": [110.0, 100.0, 0.3, 1.2]}, "virtual_sdcard": {"progress": 0.01}}}, "id": 1},
    {"jsonrpc": "2.0", "method": "notify_gcode_response", "params": ["// layerwatch snapshot layer=0 z=0.300"]},
    {"jsonrpc": "2.0", "method": "notify_status_update", "params": [{"gcode_move": {"gcode_position": [110.0, 100.0, 0.6, 2.0]}}, 11.0]},
    {"jsonrpc": "2.0", "method": "notify_gcode_response", "params": ["echo: unrelated"]},
    {"jsonrpc": "2.0", "method": "notify_gcode_response", "params": ["layerwatch snapshot layer=1 z=0.600"]},
    {"jsonrpc": "2.0", "method": "notify_gcode_response", "params": ["layerwatch snapshot layer=1 z=0.600"]},
    {"jsonrpc": "2.0", "method": "notify_status_update", "params": [{"print_stats": {"state": "paused"}}, 12.0]},
]


def test_recorded_frames():
    p = MoonrakerPrinter("moonraker://127.0.0.1:9", push=False)
    try:
        for f in FRAMES:
            p.handle_frame(json.dumps(f))
        p.handle_frame("not json")
        trig = p.poll_triggers()
        assert [(t.layer, t.z) for t in trig] == [(0, 0.3), (1, 0.6)]
        st = p._status()
        assert (st.state, st.file, st.z, st.layer) == ("paused", "part_lw.gcode", 0.6, 1)
        assert SUBSCRIBE["method"] == "printer.objects.subscribe" and "print_stats" in SUBSCRIBE["params"]["objects"]
    finally:
        p.close()


def test_unreachable_moonraker_is_a_clear_error():
    with MoonrakerPrinter("moonraker://127.0.0.1:9", push=False, timeout_s=1) as p, pytest.raises(PrinterError, match="unreachable"):
        p.pause()


def test_klippy_connection_notifications_override_print_stats():
    with MoonrakerPrinter("moonraker://127.0.0.1:9", push=False) as p:
        p.handle_frame({"jsonrpc": "2.0", "method": "notify_status_update", "params": [{"print_stats": {"state": "printing"}}, 1.0]})
        assert p._status().state == "printing"
        p.handle_frame({"jsonrpc": "2.0", "method": "notify_klippy_shutdown"})
        assert p._status().state == "error"  # print_stats still says "printing" / "paused" after M112
        p.handle_frame({"jsonrpc": "2.0", "method": "notify_klippy_disconnected"})
        assert p._status().state == "offline"
        p.handle_frame({"jsonrpc": "2.0", "method": "notify_klippy_ready"})
        assert p._status().state == "printing"
