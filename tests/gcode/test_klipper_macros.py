"""`layerwatch klipper-config`: the macro file, its shipped copy, and the host's acknowledgement."""

from __future__ import annotations

from pathlib import Path

from layerwatch.cli import main
from layerwatch.gcode.klipper_macros import KLIPPER_MACRO, ack_script, klipper_config

SHIPPED = Path(__file__).resolve().parents[2] / "integrations" / "klipper" / "layerwatch.cfg"


def test_klipper_config_prints_the_macro_file(capsys):
    assert main(["klipper-config"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("# layerwatch.cfg, written by `layerwatch klipper-config` (layerwatch ")
    for section in ("[respond]", "[gcode_macro LAYERWATCH_SNAPSHOT]", "[gcode_macro LAYERWATCH_WAIT]"):
        assert f"\n{section}\n" in out
    assert out.split("\n", 1)[1] == KLIPPER_MACRO


def test_shipped_copy_is_the_generated_file():
    assert SHIPPED.read_text().split("\n", 1)[1] == KLIPPER_MACRO


def test_hold_steps_and_ack():
    text = klipper_config()
    assert "G4 P500" in text and "variable_taken: -1" in text and "VARIABLE=misses" in text
    assert ack_script(7) == "SET_GCODE_VARIABLE MACRO=LAYERWATCH_SNAPSHOT VARIABLE=taken VALUE=7"
