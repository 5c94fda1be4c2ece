"""farm.toml is validated at the edge: one line naming the printer and key, exit 2."""

from __future__ import annotations

from pathlib import Path

import pytest

from layerwatch.cli import main
from layerwatch.errors import ConfigError
from layerwatch.farm import load_farm, parse_farm

GOOD = """
[farm]
workers = 3
queue_frames = 4

[[printers]]
name = "p01"
printer = "virtual"
camera = "sim"
layer_seconds = 1.5
failure = "spaghetti"
onset = 8
[printers.settings]
policy = { pause_ratio = 0.05 }

[[printers]]
name = "p02"
"""


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "farm.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_good_farm_file_reads_every_key(tmp_path):
    cfg = load_farm(_write(tmp_path, GOOD))
    assert (cfg.workers, cfg.queue_frames, cfg.scheduler) == (3, 4, None)
    a, b = cfg.printers
    assert (a.name, a.printer, a.camera, a.layer_seconds, a.failure, a.onset) == ("p01", "virtual", "sim", 1.5, "spaghetti", 8)
    assert a.settings == {"policy": {"pause_ratio": 0.05}}
    assert (b.name, b.failure, b.layer_seconds) == ("p02", None, 1.0)


@pytest.mark.parametrize("extra, words", [
    ('layer_secs = 2', ["'p02'", "unknown key 'layer_secs'"]),
    ('layer_seconds = nan', ["'p02'", "layer_seconds", "out of range"]),
    ('layer_seconds = inf', ["'p02'", "layer_seconds"]),
    ('layer_seconds = -1', ["'p02'", "layer_seconds"]),
    ('onset = 2.5', ["'p02'", "onset", "integer"]),
    ('failure = "gremlins"', ["'p02'", "failure", "spaghetti"]),
    ('printer = "prusa://x"', ["'p02'", "printer", "octoprint://"]),
    ('camera = "rtsp://cam"', ["'p02'", "camera"]),
    ('camera = "http://cam/snap"', ["'p02'", "camera_model"]),
    ('printer = "octoprint://h:80?key=SECRET"\ncamera = "ftp://x"', ["'p02'", "camera", "'ftp://x'"]),
    ('settings = { policy = { pause_ratio = nan } }', ["'p02'", "policy.pause_ratio", "finite"]),
    ('settings = { bogus = { a = 1 } }', ["'p02'", "bogus"]),
    ('gcode = "missing.gcode"', ["'p02'", "gcode", "no such file"]),
    ('park_tolerance = 0', ["'p02'", "park_tolerance", "false"]),
    ('park_tolerance = nan', ["'p02'", "park_tolerance"]),
    ('park_tolerance = true', ["'p02'", "park_tolerance"]),
])
def test_each_mistake_is_one_line_naming_printer_and_key(tmp_path, extra, words):
    with pytest.raises(ConfigError) as err:
        load_farm(_write(tmp_path, GOOD + extra + "\n"))
    msg = str(err.value)
    assert "\n" not in msg and all(w in msg for w in words), msg
    assert "SECRET" not in msg


def test_image_store_and_park_check_keys(tmp_path):
    cfg = load_farm(_write(tmp_path, "[farm]\nimages = \"pics\"\nkeep_mb = 500\nkeep_jobs = 20\n"
                                     "[[printers]]\nname = \"a\"\npark_tolerance = 2.5\n"
                                     "[[printers]]\nname = \"b\"\npark_tolerance = false\n[[printers]]\nname = \"c\"\n"))
    assert (cfg.images, cfg.keep_mb, cfg.keep_jobs) == (tmp_path / "pics", 500.0, 20) and cfg.images.is_dir()
    assert [p.park_tolerance_mm for p in cfg.printers] == [2.5, None, 1.0]
    with pytest.raises(ConfigError, match="keep_jobs"):
        parse_farm({"farm": {"keep_jobs": 0}, "printers": [{"name": "a"}]}, tmp_path)


def test_duplicate_names_and_top_level_mistakes(tmp_path):
    with pytest.raises(ConfigError, match="'p01': name is used twice"):
        load_farm(_write(tmp_path, GOOD + '[[printers]]\nname = "p01"\n'))
    with pytest.raises(ConfigError, match="workers"):
        parse_farm({"farm": {"workers": float("inf")}, "printers": [{"name": "a"}]}, tmp_path)
    with pytest.raises(ConfigError, match="unknown key 'worker'"):
        parse_farm({"farm": {"worker": 2}, "printers": [{"name": "a"}]}, tmp_path)
    with pytest.raises(ConfigError, match="no \\[\\[printers\\]\\]"):
        parse_farm({}, tmp_path)
    with pytest.raises(ConfigError, match="name"):
        parse_farm({"printers": [{"name": "../etc"}]}, tmp_path)


def test_serve_farm_refuses_a_bad_file_with_exit_2(tmp_path, capsys):
    bad = _write(tmp_path, GOOD + "layer_seconds = nan\n")
    code = main(["serve", "--db", str(tmp_path / "h.db"), "--farm", str(bad)])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2 and len(err) == 1 and "'p02'" in err[0] and "layer_seconds" in err[0], err
    code = main(["serve", "--db", str(tmp_path / "h.db"), "--scheduler", "tcp://x:8786"])
    assert code == 2
