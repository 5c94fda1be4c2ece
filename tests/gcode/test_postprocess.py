"""Snapshot block: triggers, the bed it parks on, exact restore under each firmware, hold at the park spot."""

from __future__ import annotations

import re

import numpy as np
import pytest

from layerwatch.errors import ConfigError
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.bed import parse_bed
from layerwatch.gcode.firmware_model import FIRMWARES, KLIPPER, MARLIN, REPRAP, check_prepared
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.gcode.settings import PrinterProfile, SnapshotSettings
from layerwatch.gcode.snapshot import prepare_gcode

ENDER = "; bed_shape = 5x0,215x0,215x220,5x220\n; max_print_height = 250\n"


def part(n=4, head="G90\nM82\n", bed=ENDER, retract=0.0) -> bytes:
    """A 10 mm square per layer at X/Y 100..110; absolute E unless ``head`` says otherwise."""
    out, e = [bed + head], 0.0
    for k in range(n):
        z = 0.2 * (k + 1)
        out.append(f";LAYER_CHANGE\n;Z:{z:.1f}\nG1 Z{z:.1f} F600\nG1 X100 Y100 F9000\n")
        if retract and k:
            e += retract
            out.append(f"G1 E{e:.3f} F2400\n")
        for x, y in [(110, 100), (110, 110), (100, 110), (100, 100)]:
            e += 0.5
            out.append(f"G1 X{x} Y{y} E{e:.3f} F1800\n")
        if retract:
            e -= retract
            out.append(f"G1 E{e:.3f} F2400\n")
    return "".join(out).encode()


def blocks(out: bytes) -> list[list[str]]:
    text = out.decode()
    return [b.split("; layerwatch snapshot block end")[0].splitlines()[1:]
            for b in text.split("; layerwatch snapshot block: ")[1:]]


@pytest.mark.parametrize(
    "profile,pattern",
    [
        ("octoprint", r"^@layerwatch snapshot layer=2 z=0\.600$"),
        ("octoprint", r"^M118 E1 layerwatch snapshot layer=2 z=0\.600$"),
        ("klipper", r"^LAYERWATCH_SNAPSHOT LAYER=2 Z=0\.600$"),
        ("klipper", r"^LAYERWATCH_WAIT LAYER=2 STEP=19 OF=20$"),
        ("timelapse", r"^TIMELAPSE_TAKE_FRAME$"),
        ("timelapse", r'^RESPOND MSG="layerwatch snapshot layer=2 z=0\.600"$'),
        ("m240", r"^M240$"),
        ("paper", r"^M118 E1 layerwatch snapshot layer=2 z=0\.600$"),
    ],
)
def test_trigger_formats(profile, pattern):
    out = insert_snapshots(part(), SnapshotSettings(profile=profile), PrinterProfile()).decode()
    assert re.search(pattern, out, re.M)


def test_paper_profile_writes_no_tool_change_or_pin_unless_configured():
    out = insert_snapshots(part(), SnapshotSettings(profile="paper"), PrinterProfile()).decode()
    assert not re.search(r"(?m)^(T\d|M42)", out)
    snap = SnapshotSettings(profile="paper", light_tool=1, indicator_pin=4)
    out = insert_snapshots(part(), snap, PrinterProfile()).decode()
    assert re.search(r"(?m)^T1 ; light platform on", out) and re.search(r"(?m)^M42 P4 S255", out)
    assert re.search(r"(?m)^T0 ; back to the print tool", out)


def test_hold_happens_at_the_park_spot_before_the_return():
    out = insert_snapshots(part(), SnapshotSettings(profile="octoprint", settle_ms=1500), PrinterProfile())
    block = blocks(out)[0]
    heads = [ln.split()[0] for ln in block]
    park, m400, trig, g4 = (heads.index(h) for h in ("G1", "M400", "@layerwatch", "G4"))
    park = block.index("G1 X210 Y215 F9000")
    back = block.index("G1 X100 Y100 F9000")
    assert park < m400 < trig < g4 < back and block[g4] == "G4 P1500"
    assert [ln for ln in block if ln.startswith("G4")] == ["G4 P1500"]


def test_park_comes_from_the_files_bed_away_from_the_part():
    # Ender-3 V2 bed_shape 5..215 x 0..220; part at 100..110: the corner pulled 5 mm in that is farthest
    # from the part is (210, 215) (distances to the part box: 145.0 vs 137.9, 138.3, 130.9)
    r = prepare_gcode(part(), SnapshotSettings())
    assert r.park_xy_mm == (210.0, 215.0) and r.bed.source == "bed_shape"
    far = part().replace(b"X100", b"X190").replace(b"X110", b"X200").replace(b"Y100", b"Y190").replace(
        b"Y110", b"Y200")
    assert prepare_gcode(far, SnapshotSettings()).park_xy_mm == (10.0, 5.0)


@pytest.mark.parametrize("park", [(300.0, 300.0), (2.0, 100.0), (100.0, 221.0)])
def test_park_outside_the_bed_is_refused(park):
    with pytest.raises(ConfigError, match="outside the bed"):
        insert_snapshots(part(), SnapshotSettings(park_xy_mm=park), PrinterProfile())


@pytest.mark.parametrize("field,value", [("park_xy_mm", (float("nan"), float("nan"))), ("lift_mm", float("inf")),
                                         ("retract_mm", float("nan")), ("travel_feed_mm_min", float("inf")),
                                         ("every_n_layers", 0), ("lift_mm", -1.0), ("settle_ms", 10)])
def test_non_finite_or_out_of_range_settings_are_refused(field, value):
    with pytest.raises(ValueError):
        SnapshotSettings(**{field: value})


def test_bed_option_and_part_off_the_bed():
    assert parse_bed("220x230x250").bounds == (0.0, 0.0, 220.0, 230.0)
    assert parse_bed("5,0;215,0;215,220;5,220").contains(6, 1)
    for bad in ("0x0", "nanx200", "220", "a,b;c", "infx10"):
        with pytest.raises(ConfigError):
            parse_bed(bad)
    with pytest.raises(ConfigError, match="not the bed it was sliced for"):
        prepare_gcode(part(bed=""), SnapshotSettings(), bed=parse_bed("50x50"))


def test_lift_never_above_the_beds_height():
    r = prepare_gcode(part(bed="; bed_shape = 0x0,200x0,200x200,0x200\n; max_print_height = 3\n"),
                      SnapshotSettings(lift_mm=5))
    lifts = [float(v) for v in re.findall(r"(?m)^G1 Z([\d.]+) F600$", r.data.decode())]
    assert max(lifts) == 3.0 and any("lift less" in n for n in r.notes)


def test_every_n_and_last_layer():
    out = insert_snapshots(part(7), SnapshotSettings(every_n_layers=3), PrinterProfile())
    layers = re.findall(rb"snapshot block: layer (\d+)", out)
    assert [int(v) for v in layers] == [2, 5, 6]


# --- the 314.6 mm retraction: the block before this fix, hand-computed --------------------------------

#: the block the old post-processor wrote after layer 0 (profile octoprint, retract 1, lift 5, park 250,210)
OLD_BLOCK = """; layerwatch snapshot block: layer 0 z=0.200
M400
G21
G91
M83
G1 E-1 F2400
G1 Z5 F9000
G90
G1 X250 Y210 F9000
M400
@layerwatch snapshot layer=0 z=0.200
M118 E1 layerwatch snapshot layer=0 z=0.200
G1 X{x} Y{y} F9000
G1 Z0.2 F9000
G1 E1 F2400
G4 P500
G21
G90
M82
G1 F1800
; layerwatch snapshot block end
"""


def marlin_file(e_end: float) -> tuple[bytes, bytes]:
    """A layer ending at absolute E = ``e_end`` (M82), then the next layer's first move; with and without OLD_BLOCK."""
    head = "; bed_shape = 0x0,250x0,250x210,0x210\nG90\nM82\nG92 E0\nG1 Z0.2 F600\nG1 X10 Y10 F9000\n"
    layer0 = f"G1 X60 Y10 E{e_end - 0.5:.2f} F1800\nG1 X60 Y11 E{e_end:.2f}\n"
    tail = f"G1 Z0.4 F600\nG1 X10 Y11 E{e_end + 1.0:.2f}\n"
    return (head + layer0 + tail).encode(), (head + layer0 + OLD_BLOCK.format(x=60, y=11) + tail).encode()


def test_old_block_retracts_314_6_mm_under_marlin_only():
    """Marlin: G90 makes E absolute again, so `G1 E1` after E=315.58 pulls 315.58 - 1 = 314.58 mm back
    on top of the 1 mm retraction; E ends at 1, not 315.58: -314.58 mm of filament over the block."""
    original, old = marlin_file(315.58)
    bed = parse_bed("250x210")
    v = check_prepared(old, MARLIN, bed, original=original)
    kinds = {x.kind for x in v}
    assert {"e_not_restored", "slicer_moves_changed"} <= kinds
    moved = [x for x in v if "filament moved" in x.detail][0]
    assert "-314.5800" in moved.detail
    logical = [x for x in v if "logical E" in x.detail][0]
    assert "1.00000 after the block, 315.58000 before" in logical.detail
    # the same lines are harmless for E under Klipper (absolute_extrude stays False) and RRF (G90 is axes only)
    for fw in (KLIPPER, REPRAP):
        assert not [x for x in check_prepared(old, fw, bed, original=original) if x.kind == "e_not_restored"]
    # and the old block also dwells on the part after the return
    assert "dwell_on_part" in kinds


def test_old_block_absolute_e_slic3r_case_4_9_mm():
    """An absolute-E file at E=5.9: `G1 E1` after G90 goes from 4.9 to 1: 3.9 mm more, 4.9 mm in all, then a blob."""
    original, old = marlin_file(5.9)
    v = check_prepared(old, MARLIN, parse_bed("250x210"), original=original)
    assert any("filament moved by -4.9000" in x.detail for x in v)


def test_new_block_restores_e_under_every_firmware():
    data = part(4)
    for fw in FIRMWARES:
        out = insert_snapshots(data, SnapshotSettings(profile="octoprint"), firmware=fw)
        assert check_prepared(out, fw, parse_bed("5,0;215,0;215,220;5,220"), original=data) == []
    block = blocks(insert_snapshots(data, SnapshotSettings(), firmware=MARLIN))[0]
    # G90 first, then M83: the order that keeps E relative inside the block under Marlin
    assert block[:2] == ["G90", "M83"] and "G92 E2" in block and block[-3:-1] == ["G90", "M82"]


@pytest.mark.parametrize("head", ["G90\nM83\n", "G91\nM83\n", "G90\nM82\n", "G91\nM82\n", "M83\nG90\n",
                                  "G21\nG90\nM82\nT1\n", "M82\nG91\n"])
@pytest.mark.parametrize("fw", FIRMWARES)
def test_modal_state_restored_exactly(head, fw):
    """Every combination of the two modes, in both orders, under each firmware's rules: 0 violations."""
    rel = "G91" in head
    body = "G1 Z0.2 F600\n" + "".join(
        f"G1 X{1 if rel else 100 + k} Y0 E0.5 F1234\n" for k in range(30)) + "G1 Z0.2\n"
    data = (head + body).encode()
    out = insert_snapshots(data, SnapshotSettings(), bed=parse_bed("2000x2000"), firmware=fw)
    assert check_prepared(out, fw, parse_bed("2000x2000"), original=data) == []


def test_slicer_retraction_counts_bowden_5mm_is_not_doubled():
    """A Bowden file retracting 5 mm after each layer: the block goes after that retraction and adds none."""
    data = part(4, retract=5.0)
    out = insert_snapshots(data, SnapshotSettings(retract_mm=1.0), PrinterProfile())
    for block in blocks(out):
        assert not [ln for ln in block if re.match(r"G1 E", ln)]
    text = out.decode()
    assert re.search(r"G1 E-?\d+\.\d+ F2400\n; layerwatch snapshot block: layer 0", text)
    for fw in FIRMWARES:
        assert check_prepared(out, fw, parse_bed("5,0;215,0;215,220;5,220"), original=data) == []


def test_file_retract_length_is_used_when_not_set():
    data = part(3, head="; retract_length = 5\nG90\nM82\n")
    block = blocks(insert_snapshots(data, SnapshotSettings()))[0]
    assert "G1 E-5 F2400" in block and "G1 E5 F2400" in block


def test_firmware_retraction_cooperates():
    head = "G90\nM83\n"
    body = "".join(f"G1 Z{0.2 * (k + 1):.1f} F600\nG11\nG1 X100 Y100 F9000\nG1 X110 Y100 E0.5 F1800\n"
                   f"G1 X110 Y110 E0.5\nG10\n" for k in range(3))
    data = (ENDER + head + body).encode()
    out = insert_snapshots(data, SnapshotSettings())
    for block in blocks(out):  # the slicer's G10 already retracted: no G10/G11 and no E move in the block
        assert not [ln for ln in block if ln.startswith(("G10", "G11", "G1 E"))]
    no_retract = data.replace(b"G10\n", b"").replace(b"G11\n", b"") + b"G10\nG11\n"
    block = blocks(insert_snapshots(no_retract, SnapshotSettings()))[0]
    assert "G10" in block and "G11" in block and not [ln for ln in block if ln.startswith("G1 E")]
    for fw in FIRMWARES:
        assert check_prepared(out, fw, parse_bed("5,0;215,0;215,220;5,220"), original=data) == []


def test_unknown_firmware_with_ambiguous_e_mode_is_refused():
    data = (ENDER + "M83\nG90\n" + "".join(f"G1 Z0.2\nG1 X{100 + k} Y100 E0.5 F1800\n" for k in range(30))).encode()
    with pytest.raises(ConfigError, match="--firmware"):
        insert_snapshots(data, SnapshotSettings())
    insert_snapshots(data, SnapshotSettings(), firmware=MARLIN)


def test_inches_and_offsets_restored():
    data = b"G21\nG90\nM82\nG92 X-50 Y-50\nG20\nG1 Z0.01\n" + b"".join(
        f"G1 X{1 + k / 100:.2f} Y1 E{k / 100:.2f} F60\n".encode() for k in range(1, 30))
    bed = parse_bed("250x210")
    out = insert_snapshots(data, SnapshotSettings(park_xy_mm=(200.0, 200.0)), bed=bed, firmware=MARLIN)
    assert check_prepared(out, MARLIN, bed, original=data) == []
    # park at the physical (200, 200) written in logical mm (G92 offset 50 mm), inside a G21 section
    block = blocks(out)[0]
    assert block[0] == "G21" and "G1 X150 Y150 F9000" in block and "G20" in block


def test_checker_flags_tool_change_pin_write_and_off_bed():
    data = part(2)
    out = insert_snapshots(data, SnapshotSettings(profile="paper", light_tool=1, indicator_pin=4))
    kinds = {v.kind for v in check_prepared(out, MARLIN, parse_bed("5,0;215,0;215,220;5,220"), original=data)}
    assert kinds == {"tool_change", "pin_write"}
    out = insert_snapshots(data, SnapshotSettings())
    v = check_prepared(out, MARLIN, parse_bed("100x100"))
    assert {x.kind for x in v} == {"off_bed"}


def test_crlf_kept_and_layers_equal():
    data = part(3).replace(b"\n", b"\r\n")
    out = insert_snapshots(data, SnapshotSettings(profile="m240"), PrinterProfile())
    assert b"\nM240\r\n" in out and out.count(b"\n") == out.count(b"\r\n")
    a, b = read_toolpath(data), read_toolpath(out)
    assert [lay.extrusion_mm for lay in a.layers] == [lay.extrusion_mm for lay in b.layers]
    np.testing.assert_allclose([lay.z for lay in a.layers], [lay.z for lay in b.layers])


def test_words_without_spaces_are_followed():
    """MeatPack-decoded .bgcode writes `G1X10Y5E.2`: the block must return to where the layer really ended."""
    data = part(3).replace(b"G1 X", b"G1X").replace(b" Y", b"Y").replace(b" E", b"E").replace(b" F", b"F")
    block = blocks(insert_snapshots(data, SnapshotSettings(), firmware=MARLIN))[0]
    assert "G1 X100 Y100 F9000" in block and "G1 Z0.2 F600" in block
    assert check_prepared(insert_snapshots(data, SnapshotSettings(), firmware=MARLIN), MARLIN,
                          parse_bed("5,0;215,0;215,220;5,220"), original=data) == []
