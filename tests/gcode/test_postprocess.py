"""Snapshot block: trigger formats, clamping, exact modal-state restore, every-N."""

from __future__ import annotations

import re

import numpy as np
import pytest

from layerwatch.gcode import read_toolpath
from layerwatch.gcode.postprocess import KLIPPER_MACRO, insert_snapshots
from layerwatch.gcode.reader import run
from layerwatch.gcode.settings import PrinterProfile, SnapshotSettings


def part(n=4, head="G90\nM82\n", hop=False) -> bytes:
    out, e = [head], 0.0
    for k in range(n):
        z = 0.2 * (k + 1)
        out.append(f";LAYER_CHANGE\n;Z:{z:.1f}\nG1 Z{z:.1f} F600\nG1 X100 Y100 F9000\n")
        for x, y in [(110, 100), (110, 110), (100, 110), (100, 100)]:
            e += 0.5
            out.append(f"G1 X{x} Y{y} E{e:.3f} F1800\n")
    return "".join(out).encode()


@pytest.mark.parametrize(
    "profile,pattern",
    [
        ("octoprint", r"^@layerwatch snapshot layer=2 z=0\.600$"),
        ("octoprint", r"^M118 E1 layerwatch snapshot layer=2 z=0\.600$"),
        ("klipper", r"^LAYERWATCH_SNAPSHOT LAYER=2 Z=0\.600$"),
        ("timelapse", r"^TIMELAPSE_TAKE_FRAME$"),
        ("timelapse", r'^RESPOND MSG="layerwatch snapshot layer=2 z=0\.600"$'),
        ("m240", r"^M240$"),
        ("paper", r"^T1 ; light platform on$"),
        ("paper", r"^M42 P4 S255 ; indicator on$"),
    ],
)
def test_trigger_formats(profile, pattern):
    out = insert_snapshots(part(), SnapshotSettings(profile=profile), PrinterProfile()).decode()
    assert re.search(pattern, out, re.M)


def test_block_order_follows_table_1():
    out = insert_snapshots(part(), SnapshotSettings(profile="klipper"), PrinterProfile()).decode()
    block = out.split("; layerwatch snapshot block: layer 0")[1].split("block end")[0].splitlines()[1:]
    heads = [ln.split()[0] for ln in block if ln]
    assert heads[:4] == ["M400", "G21", "G91", "M83"]
    i = {h: heads.index(h) for h in ("LAYERWATCH_SNAPSHOT", "G4")}
    assert heads.index("G1") < i["LAYERWATCH_SNAPSHOT"] < i["G4"]
    assert "G4 P500" in block


def test_every_n_and_last_layer():
    out = insert_snapshots(part(7), SnapshotSettings(every_n_layers=3), PrinterProfile())
    layers = re.findall(rb"snapshot block: layer (\d+)", out)
    assert [int(v) for v in layers] == [2, 5, 6]


def test_park_and_lift_clamped_to_volume():
    printer = PrinterProfile(volume_max_mm=(200.0, 180.0, 0.7))
    snap = SnapshotSettings(park_xy_mm=(500.0, -20.0), lift_mm=5.0)
    out = insert_snapshots(part(4), snap, printer).decode()
    assert "G1 X200 Y0 F9000" in out
    lifts = [float(v) for v in re.findall(r"^G1 Z([\d.]+) F9000$", out, re.M)]
    # relative lifts: up to the volume top, never down (layer 3 at 0.8 > 0.7: no lift)
    assert lifts[0] == pytest.approx(0.5) and min(lifts) >= 0


@pytest.mark.parametrize(
    "head,expect",
    [
        ("G90\nM82\n", (1, 0, 0)),
        ("G90\nM83\nT1\n", (1, 1, 1)),
        ("G91\nM83\nT2\n", (0, 1, 2)),
    ],
)
def test_modal_state_restored_exactly(head, expect):
    if head.startswith("G91"):
        data = (head + "G1 Z0.2\nG1 X1 Y0 E0.5 F1234\nG1 X0 Y1 E0.5\n").encode()
    else:
        data = part(2, head=head)
        if "M83" in head:
            data = data.replace(b"E0.500", b"E0.5").replace(b"E1.000", b"E0.5")
    out = insert_snapshots(data, SnapshotSettings(profile="octoprint"), PrinterProfile())
    end_line = out.count(b"\n") + 1
    before = run(data, np.array([data.count(b"\n") + 1], np.int64))[5][0]
    after = run(out, np.array([end_line], np.int64))[5][0]
    np.testing.assert_allclose(after, before, atol=1e-9)  # position, E, feed, modes, tool
    assert (before[8], before[9], before[10]) == expect


def test_inches_and_offsets_restored():
    data = b"G21\nG92 X-50 Y-50\nG20\nG1 Z0.01\nG1 X1 Y1 E0.01 F60\nG1 X2 Y1 E0.02\n"
    out = insert_snapshots(data, SnapshotSettings(), PrinterProfile())
    b = run(data, np.array([7], np.int64))[5][0]
    a = run(out, np.array([out.count(b"\n") + 1], np.int64))[5][0]
    np.testing.assert_allclose(a, b, atol=1e-9)
    park = re.search(rb"G1 X(\S+) Y(\S+) F9000", out)
    # park at the physical corner (250, 210) written in logical coordinates (offset 50 mm)
    assert (float(park.group(1)), float(park.group(2))) == (200.0, 160.0)


def test_crlf_kept_and_layers_equal():
    data = part(3).replace(b"\n", b"\r\n")
    out = insert_snapshots(data, SnapshotSettings(profile="m240"), PrinterProfile())
    assert b"\nM240\r\n" in out and out.count(b"\n") == out.count(b"\r\n")
    a, b = read_toolpath(data), read_toolpath(out)
    assert [lay.extrusion_mm for lay in a.layers] == [lay.extrusion_mm for lay in b.layers]


def test_klipper_macro_text():
    assert "[gcode_macro LAYERWATCH_SNAPSHOT]" in KLIPPER_MACRO
    assert 'RESPOND MSG="layerwatch snapshot layer={layer}' in KLIPPER_MACRO
