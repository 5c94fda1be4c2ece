"""Dialect semantics: volumetric E (UltiGCode, M200 D), M221 flow, E-only flushes, FlashPrint's
layer thickness, the FlashForge .gx container."""

from __future__ import annotations

import math
import struct

import pytest
from gcode_refs import shared_gcode_files

from layerwatch.errors import GcodeError
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.gx import decode_gx

SQUARE = b"G1 X10 Y0 E{e}\nG1 X10 Y10 E{e2}\nG1 X0 Y10 E{e3}\nG1 X0 Y0 E{e4}\n"


def _square(per_side: float, absolute: bool = True) -> bytes:
    vals = [per_side * k for k in (1, 2, 3, 4)] if absolute else [per_side] * 4
    return SQUARE.replace(b"{e}", b"%g" % vals[0]).replace(b"{e2}", b"%g" % vals[1]).replace(
        b"{e3}", b"%g" % vals[2]).replace(b"{e4}", b"%g" % vals[3])


def _layered(body: bytes, head: bytes = b"") -> bytes:
    return head + b"G21\nG90\nM82\nG92 E0\nG1 Z0.2 F600\nG1 X0 Y0\n" + body


def test_ultigcode_e_is_volume():
    area = math.pi * 2.85**2 / 4
    data = _layered(_square(area), head=b";FLAVOR:UltiGCode\n")  # 1 mm of 2.85 mm filament per side, as mm^3
    tp = read_toolpath(data)
    assert tp.volumetric and tp.filament_diameter == 2.85
    assert tp.extrusion_mm == pytest.approx(4.0)
    tp175 = read_toolpath(data, filament_diameter=1.75)
    assert tp175.extrusion_mm == pytest.approx(4 * area / (math.pi * 1.75**2 / 4))


def test_ultigcode_material_header_is_a_volume_statement():
    area = math.pi * 2.85**2 / 4
    head = b";FLAVOR:UltiGCode\n;TIME:100\n;MATERIAL:%d\n;MATERIAL2:0\n" % round(4 * area)
    tp = read_toolpath(_layered(_square(area), head=head))
    assert tp.statements.filament_cm3 == pytest.approx(4 * area / 1000, abs=1e-3)
    assert tp.statements.filament_mm is None  # the header states a volume only
    assert tp.filament_commanded_mm * tp.filament_area_mm2 / 1000 == pytest.approx(tp.statements.filament_cm3, abs=1e-3)


def test_m200_d_switches_to_volumes_and_back():
    area = math.pi * 1.75**2 / 4
    body = b"M83\nM200 D1.75\nG1 X10 Y0 E%g\nM200 D0\nG1 X10 Y10 E1\n" % area
    tp = read_toolpath(_layered(body))
    assert tp.volumetric
    assert list(tp.e) == pytest.approx([1.0, 1.0])


def test_m221_scales_what_is_fed_not_what_is_commanded():
    tp = read_toolpath(_layered(b"M83\nM221 S95\n" + _square(1.0, absolute=False)))
    assert tp.filament_commanded_mm == pytest.approx(4.0)
    assert tp.extrusion_mm == pytest.approx(3.8)
    assert tp.filament_fed_mm == pytest.approx(3.8)


def test_m221_per_tool():
    tp = read_toolpath(_layered(b"M83\nM221 T1 S50\nT0\nG1 X10 Y0 E1\nT1\nG1 X10 Y10 E1\n"))
    assert list(tp.e) == pytest.approx([1.0, 0.5])
    assert list(tp.tool) == [0, 1]


def test_e_only_flush_is_fed_but_not_geometry():
    body = b"M83\nG1 E50 F200\nG1 E-1\nG1 E1\n" + _square(1.0, absolute=False) + b"G1 E-0.8\n"
    tp = read_toolpath(_layered(body))
    assert tp.n_segments == 4 and tp.extrusion_mm == pytest.approx(4.0)
    assert tp.filament_fed_mm == pytest.approx(54.0)  # the retract/unretract pair counts once
    assert tp.filament_commanded_mm == pytest.approx(4.0)


def test_flashprint_layer_tag_is_thickness():
    path = next((p for p in shared_gcode_files() if p.name.startswith("flashprint")), None)
    if path is None:
        pytest.skip("shared data absent")
    tp = read_toolpath(path)
    zs = [lay.z for lay in tp.layers]
    assert zs == sorted(zs) and zs[-1] > 4.5  # rises with the print, not 0.18 .. 0.4
    # each tag's thickness is the step from the layer below (raft layers included)
    assert all(0.05 < lay.height <= 0.5 for lay in tp.layers[1:])


def _gx(gcode: bytes, gcode_at: int | None = None) -> bytes:
    bmp = b"BM" + bytes(100)
    at = 58 + len(bmp) if gcode_at is None else gcode_at
    head = b"xgcode 1.0\n\x00" + struct.pack("<iIII", 0, 58, at, at) + struct.pack("<III", 600, 1234, 0)
    head += struct.pack("<9H", 11, 180, 0, 2, 60, 60, 210, 0, 1)
    assert len(head) == 58
    return head + bmp + gcode


def test_gx_container_is_read():
    path = next((p for p in shared_gcode_files() if p.name.startswith("flashprint")), None)
    if path is None:
        pytest.skip("shared data absent")
    text = path.read_bytes()
    a, b = read_toolpath(text), read_toolpath(_gx(text))
    assert a.n_layers == b.n_layers and a.n_segments == b.n_segments
    assert b.statements.filament_mm == pytest.approx(1234.0)  # from the .gx header
    assert b.generator.name == "FlashPrint"


def test_damaged_gx_is_a_one_line_error():
    with pytest.raises(GcodeError, match="G-code at byte"):
        decode_gx(_gx(b"G1 X1\n", gcode_at=10**9))
    with pytest.raises(GcodeError, match="truncated"):
        read_toolpath(b"xgcode 1.0\n\x00\x00")
