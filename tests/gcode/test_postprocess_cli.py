"""`layerwatch gcode prepare`: every bad number or park spot is one line and exit 2; the bed comes from the file."""

from __future__ import annotations

import pytest
from gcode_refs import shared_gcode_files

from layerwatch.cli import main

ENDER = next((p for p in shared_gcode_files() if p.name == "prusaslicer-2.7.4_spiral-vase.gcode"), None)
pytestmark = pytest.mark.skipif(ENDER is None, reason="shared data absent")


@pytest.mark.parametrize("extra,says", [
    (["--park", "nan,nan"], "finite"),
    (["--park", "300,300"], "outside the bed"),
    (["--park", "2,100"], "outside the bed"),
    (["--park", "abc"], "two numbers"),
    (["--every", "0"], "--every"),
    (["--lift", "inf"], "--lift"),
    (["--lift", "500"], "--lift"),
    (["--retract", "nan"], "--retract"),
    (["--retract", "-1"], "--retract"),
    (["--bed", "0x0"], "--bed"),
    (["--bed", "nanx200"], "--bed"),
    (["--bed", "100x100"], "not the bed it was sliced for"),
    (["--firmware", "grbl"], "--firmware"),
    (["--hold", "nan"], "--hold"),
    (["--dwell-ms", "5"], "--dwell-ms"),
])
def test_bad_values_exit_2_with_one_line(extra, says, tmp_path, capsys):
    out = tmp_path / "o.gcode"
    assert main(["gcode", "prepare", str(ENDER), "-o", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err, err
    assert not out.exists()


def test_prepare_parks_on_the_files_bed(tmp_path, capsys):
    out = tmp_path / "o.gcode"
    assert main(["gcode", "prepare", str(ENDER), "-o", str(out)]) == 0
    # the corner farthest from the part; the start G-code's purge line (front) is not part of the part
    assert "bed X 5..215, Y 0..220 mm (bed_shape), park X210 Y5" in capsys.readouterr().err
    text = out.read_text()
    assert "G1 X210 Y5 F9000" in text and "X250" not in text and "nan" not in text.lower()


def test_prepare_refuses_to_guess_the_bed(tmp_path, capsys):
    cura = next(p for p in shared_gcode_files() if p.name == "cura-2.3.1_reprap.gcode")
    out = tmp_path / "o.gcode"
    assert main(["gcode", "prepare", str(cura), "-o", str(out)]) == 2
    assert "does not say which bed" in capsys.readouterr().err and not out.exists()
    assert main(["gcode", "prepare", str(cura), "-o", str(out), "--bed", "220x220x250"]) == 0
