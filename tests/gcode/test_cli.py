"""`layerwatch gcode info|prepare` through layerwatch.cli.main."""

from __future__ import annotations

import pytest
from gcode_refs import shared_gcode_files

from layerwatch.cli import main
from layerwatch.gcode import read_toolpath


def test_info_on_example(example_gcode, capsys):
    assert main(["gcode", "info", str(example_gcode)]) == 0
    out = capsys.readouterr().out
    assert "layers" in out and "33" in out and "detection" in out and "tags:prusaslicer" in out


@pytest.mark.parametrize("path", [p for p in shared_gcode_files() if p.suffix == ".gcode"][:20:4],
                         ids=lambda p: p.name)
def test_info_on_shared(path, capsys):
    assert main(["gcode", "info", str(path)]) == 0
    assert "Z range" in capsys.readouterr().out


def test_prepare_klipper_round_trip(example_gcode, tmp_path, capsys):
    out = tmp_path / "out.gcode"
    assert main(["gcode", "prepare", str(example_gcode), "--profile", "klipper", "-o", str(out)]) == 0
    a, b = read_toolpath(example_gcode), read_toolpath(out)
    assert a.n_layers == b.n_layers == 33
    assert [lay.extrusion_mm for lay in a.layers] == pytest.approx([lay.extrusion_mm for lay in b.layers])
    assert out.read_bytes().count(b"LAYERWATCH_SNAPSHOT LAYER=") == 33


@pytest.mark.parametrize(
    "argv",
    [
        ["gcode", "info", "/nonexistent/file.gcode"],
        ["gcode", "prepare", "/nonexistent.gcode", "-o", "x.gcode"],
        ["gcode", "prepare", "{ex}", "--profile", "nope", "-o", "{tmp}/o.gcode"],
        ["gcode", "prepare", "{ex}", "--park", "1,2,3", "-o", "{tmp}/o.gcode"],
        ["gcode", "info", "{junk}"],
    ],
)
def test_bad_input_exit_2(argv, example_gcode, tmp_path, capsys):
    junk = tmp_path / "junk.gcode"
    junk.write_bytes(b"\x00\x01\x02" * 100)
    argv = [a.format(ex=example_gcode, tmp=tmp_path, junk=junk) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err


def test_info_on_text_without_extrusion_is_a_one_line_error(tmp_path, capsys):
    text = tmp_path / "notes.gcode"
    text.write_text("hello world\nthis is not gcode\n")
    assert main(["gcode", "info", str(text)]) == 2
    err = capsys.readouterr().err
    assert "no G-code moves" in err and "Traceback" not in err
    assert len([ln for ln in err.strip().splitlines() if ln.startswith("error:")]) == 1


def test_a_bug_is_one_line_with_the_traceback_saved_not_a_traceback(example_gcode, monkeypatch, capsys):
    import layerwatch.cli.gcode as cli_gcode

    def broken(*a, **k):
        raise IndexError("tuple index out of range")

    monkeypatch.delenv("LAYERWATCH_DEBUG", raising=False)
    monkeypatch.setattr(cli_gcode, "_read_with_progress", broken)
    assert main(["gcode", "info", str(example_gcode)]) == 70
    err = capsys.readouterr().err
    line = " ".join(err.split())
    assert "Traceback" not in err and "internal error: IndexError: tuple index out of range" in line
    saved = line.split("traceback in ")[-1].strip()
    from pathlib import Path

    text = Path(saved).read_text()
    Path(saved).unlink()
    assert "Traceback" in text and "broken" in text, (saved, text[-300:])
    monkeypatch.setenv("LAYERWATCH_DEBUG", "1")
    with pytest.raises(IndexError):
        main(["gcode", "info", str(example_gcode)])
