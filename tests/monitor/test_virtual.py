from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.gcode.settings import PrinterProfile, SnapshotSettings
from layerwatch.monitor.printers.base import parse_trigger
from layerwatch.monitor.printers.virtual import VirtualPrinter


def test_parse_trigger_formats():
    assert parse_trigger("@layerwatch snapshot layer=3 z=1.200").layer == 3
    t = parse_trigger("M118 E1 layerwatch snapshot layer=4 z=1.5")
    assert (t.layer, t.z) == (4, 1.5)
    assert parse_trigger("LAYERWATCH_SNAPSHOT LAYER=5 Z=1.800").z == 1.8
    assert parse_trigger('// action: echo: layerwatch snapshot layer=6 z=2.1').layer == 6
    assert parse_trigger("; layerwatch snapshot layer=7 z=2.4") is None
    assert parse_trigger("G1 X10 Y10") is None


def _gcode(profile: str, example_gcode) -> bytes:
    return insert_snapshots(example_gcode.read_bytes(), SnapshotSettings(profile=profile), PrinterProfile())


def test_virtual_replays_triggers_in_order(example_gcode):
    data = _gcode("octoprint", example_gcode)
    assert b"@layerwatch snapshot" in data
    seen = []
    vp = VirtualPrinter(data, on_trigger=seen.append)
    layers = []
    while (t := vp.step_to_next_trigger()) is not None:
        layers.append(t.layer)
    assert layers == sorted(set(layers)) and len(layers) >= 30
    assert [t.layer for t in seen] == layers
    assert vp.status().state == "finished"


def test_virtual_klipper_profile(example_gcode):
    vp = VirtualPrinter(_gcode("klipper", example_gcode))
    first = vp.step_to_next_trigger()
    assert first is not None and first.layer == 0 and first.z > 0


def test_virtual_pause_resume_cancel():
    g = "\n".join(f"G1 Z{0.3 * (i + 1):.2f}\n@layerwatch snapshot layer={i} z={0.3 * (i + 1):.3f}\nM118 E1 layerwatch snapshot layer={i} z={0.3 * (i + 1):.3f}" for i in range(5)).encode()
    vp = VirtualPrinter(g)
    assert vp.step_to_next_trigger().layer == 0
    vp.pause()
    assert vp.status().state == "paused" and vp.step_to_next_trigger() is None
    vp.resume()
    assert vp.step_to_next_trigger().layer == 1
    assert [t.layer for t in vp.poll_triggers()] == [0, 1]
    vp.cancel()
    assert vp.status().state == "cancelled" and vp.step_to_next_trigger() is None


def test_virtual_thread_replay():
    g = "\n".join(f"@layerwatch snapshot layer={i} z={i}" for i in range(20)).encode()
    vp = VirtualPrinter(g)
    vp.start()
    vp.join(10)
    assert [t.layer for t in vp.poll_triggers()] == list(range(20))
    vp.close()
