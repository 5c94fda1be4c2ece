"""`layerwatch render`: layer specs, PNGs written, one-line errors."""

from __future__ import annotations

import cv2
import pytest
from render_parts import square_part

from layerwatch.cli import main
from layerwatch.cli import render as render_cli
from layerwatch.cli.render import parse_layers
from layerwatch.errors import RenderError


def test_parse_layers():
    assert parse_layers("10:13", 33) == [10, 11, 12]
    assert parse_layers("5", 33) == [5]
    assert parse_layers("-1", 33) == [32]
    assert parse_layers("1,4,9", 33) == [1, 4, 9]
    assert parse_layers("::10", 33) == [0, 10, 20, 30]
    assert parse_layers(None, 3) == [0, 1, 2]
    assert parse_layers("30:40", 33) == [30, 31, 32]
    for bad in ("99", "x", "40:50", "1:2:3:4"):
        with pytest.raises(RenderError):
            parse_layers(bad, 33)


@pytest.fixture()
def fake_reader(monkeypatch):
    """Stand-in for the G-code reader: a synthetic square part centred at X110 Y100."""
    part = square_part(4, center=(110.0, 100.0), size=20.0)
    monkeypatch.setattr(render_cli, "read_toolpath", lambda src, **kw: part)  # the name the verb module uses
    return part


def test_cli_writes_pngs(tmp_path, fake_reader, capsys):
    src = tmp_path / "part.gcode"
    src.write_text("; stand-in\n")
    out = tmp_path / "refs"
    rc = main(["render", str(src), "--layers", "1:3", "-o", str(out), "--mask", "--cache", str(tmp_path / "c")])
    assert rc == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["layer_0001.png", "layer_0001_mask.png", "layer_0002.png", "layer_0002_mask.png"]
    img = cv2.imread(str(out / "layer_0002.png"), cv2.IMREAD_GRAYSCALE)
    m = cv2.imread(str(out / "layer_0002_mask.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (600, 600) and m.shape == (600, 600)
    # the part is centred in the observed square and brighter than the bed
    assert img[300, 300] > 100 and img[10, 10] < 60 and m[300, 300] == 255
    assert any(p.suffix == ".npz" for p in (tmp_path / "c").rglob("*"))


def test_cli_errors_are_one_line(tmp_path, fake_reader, capsys):
    src = tmp_path / "part.gcode"
    src.write_text("; stand-in\n")
    assert main(["render", str(tmp_path / "missing.gcode")]) == 2
    assert main(["render", str(src), "--layers", "50", "-o", str(tmp_path / "o")]) == 2
    assert main(["render", str(src), "--backend", "cycles", "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 3 and all(ln.startswith("error:") for ln in lines)


def test_cli_on_bundled_example(tmp_path, example_gcode):
    """The real reader on the bundled PrusaSlicer file, with its job config."""
    from layerwatch.examples import PART_CONFIG
    from layerwatch.gcode import read_toolpath  # noqa: F401  (must exist)

    out = tmp_path / "refs"
    rc = main(["render", str(example_gcode), "--layers", "10:12", "-o", str(out), "--config", str(PART_CONFIG)])
    assert rc == 0
    img = cv2.imread(str(out / "layer_0011.png"), cv2.IMREAD_GRAYSCALE)
    assert img is not None and img.shape == (600, 600)
    assert (img > 100).mean() > 0.01


def test_cli_on_shared_real_gcode(tmp_path, shared_data):
    """A real slicer file from ../shared/data: top view centred on the part, a few layers."""
    src = shared_data / "gcode" / "prusaslicer-2.8.1_mini-cube_ascii.gcode"
    if not src.is_file():
        pytest.skip(f"{src.name} not in the shared data")
    from layerwatch.gcode import read_toolpath  # noqa: F401  (must exist)

    out = tmp_path / "refs"
    assert main(["render", str(src), "--layers", "2:4", "-o", str(out), "--mask"]) == 0
    img = cv2.imread(str(out / "layer_0003.png"), cv2.IMREAD_GRAYSCALE)
    m = cv2.imread(str(out / "layer_0003_mask.png"), cv2.IMREAD_GRAYSCALE)
    assert img is not None and m is not None and (m > 0).sum() > 500
    assert img[m > 0].mean() > img[m == 0].mean() + 40
