"""`layerwatch gcode info` shows the file's statements next to the reading and warns where
they disagree; `--json` carries both."""

from __future__ import annotations

import json

import pytest
from gcode_refs import shared_gcode_files

from layerwatch.cli import main

FILES = {p.name: p for p in shared_gcode_files()}


def _need(name):
    if name not in FILES:
        pytest.skip("shared data absent")
    return FILES[name]


def test_json_carries_reading_and_statements(capsys):
    path = _need("prusaslicer-2.9.6_xl2is-ascii-twin.gcode")
    assert main(["gcode", "info", "--json", str(path)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["statements"]["filament_mm"] == pytest.approx(5473.85)
    assert doc["statements"]["first_layer_box"] == pytest.approx([163.069, 161.819, 199.069, 197.819])
    assert doc["reading"]["generator"] == "PrusaSlicer 2.9.6"
    assert doc["reading"]["filament_commanded_mm"] == pytest.approx(5473.85, rel=0.02)
    assert doc["disagreements"] == []


def test_disagreement_is_a_warning(capsys):
    path = _need("bambustudio-2.4.0_single-layer.gcode")  # states 75.74 mm; its moves extrude 24.26 mm
    assert main(["gcode", "info", str(path)]) == 0
    cap = capsys.readouterr()
    assert "75.74" in cap.out and "file states" in cap.out
    assert "statement disagrees: filament (mm)" in cap.err.replace("\n", " ")


def test_agreeing_file_has_no_statement_warning(capsys):
    path = _need("orcaslicer-2.3.1_bambu-a1-gridfinity.gcode")
    assert main(["gcode", "info", str(path)]) == 0
    cap = capsys.readouterr()
    assert "224" in cap.out and "disagrees" not in cap.err


def test_filament_diameter_option_is_validated(capsys):
    path = _need("cura-4.10.0_m83_multi-object.gcode")
    assert main(["gcode", "info", "--filament-diameter", "0", str(path)]) == 2
    assert main(["gcode", "info", "--json", "--filament-diameter", "2.85", str(path)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["reading"]["filament_diameter_mm"] == 2.85


def test_volumetric_file_says_so(tmp_path, capsys):
    path = tmp_path / "ulti.gcode"
    path.write_bytes(b";FLAVOR:UltiGCode\nG90\nM82\nG92 E0\nG1 Z0.2\nG1 X0 Y0\nG1 X10 Y0 E6.38\nG1 X10 Y10 E12.76\n")
    assert main(["gcode", "info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "E words are volumes" in out and "2.85 mm" in out


def test_damaged_bgcode_is_exit_2_with_one_line(tmp_path, capsys):
    src = next((p for p in FILES.values() if p.suffix == ".bgcode"), None)
    if src is None:
        pytest.skip("shared data absent")
    bad = tmp_path / "cut.bgcode"
    bad.write_bytes(src.read_bytes()[:5000])
    assert main(["gcode", "info", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "cut.bgcode" in err and "export" in err
