"""Usage mistakes on every verb: one line on stderr, exit 2; --version, help texts, exit codes 1 and 70."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import typer
from cli_badlines import leaf_commands, make_fixtures

from layerwatch.cli import main
from layerwatch.cli.params import Finite, Writable, finite_of
from layerwatch.examples import PART_GCODE

EX = str(PART_GCODE)

# (argv, a phrase the one error line must contain); PNG, CAM, OUT are filled in from fixtures
USAGE_MISTAKES = [
    (["--bogus"], "No such option: --bogus"),
    (["renderr"], "Did you mean 'render'"),
    (["gcodee", "info", EX], "No such command 'gcodee'"),
    (["gcode", "infoo", EX], "No such command 'infoo'"),
    (["gcode", "info"], "Missing argument"),
    (["gcode", "info", "/proc/layerwatch-missing.gcode"], "does not exist"),
    (["gcode", "prepare", EX], "Missing option '-o' / '--output'"),
    (["gcode", "prepare", EX, "-o", "OUT/p.gcode", "--every", "0"], "'--every': '0' is out of range"),
    (["gcode", "prepare", EX, "-o", "OUT/p.gcode", "--lift", "nan"], "'--lift': 'nan' is not finite"),
    (["gcode", "prepare", EX, "-o", "OUT/p.gcode", "--retract", "-1"], "'--retract': '-1' is out of range"),
    (["gcode", "prepare", EX, "-o", "OUT/p.gcode", "--park", "nan,nan"], "--park 'nan,nan': the coordinates must be finite"),
    (["gcode", "prepare", EX, "-o", "OUT/p.gcode", "--volume", "220,inf,250"], "--volume"),
    (["gcode", "prepare", EX, "-o", "/dev/null/p.gcode"], "'/dev/null' does not exist"),
    (["compare", "PNG"], "Missing argument 'reference'"),
    (["compare", "PNG", "PNG", "--threshold", "1.5"], "'1.5' is out of range; give a finite number from 0 to 1"),
    (["compare", "PNG", "PNG", "--px-per-mm", "inf"], "'--px-per-mm': 'inf' is not finite"),
    (["compare", "PNG", "PNG", "--cell-px", "8.5"], "'8.5' is not a whole number"),
    (["compare", "PNG", "PNG", "--output"], "Option '--output' requires an argument"),
    (["render", EX, "--workers", "-1"], "'--workers'"),
    (["render", EX, "--scheduler", "nowhere"], "not a Dask scheduler address"),
    (["analyze", "PNG", "--camera", "CAM"], "Missing option '--gcode'"),
    (["analyze", "PNG", "--gcode", EX, "--camera", "CAM", "--cache", "PNG"], "is a file, not a folder"),
    (["simulate", "--width", "1e9"], "'--width': '1e9' is not a whole number"),
    (["simulate", "--seed", "-1"], "'--seed': '-1' is out of range"),
    (["simulate", "--failure", "spaghetti@3:inf"], "finite size_mm"),
    (["evaluate", "--layers", "5"], "give a whole number from 14 to 100000"),
    (["evaluate", "--margin-mm", "-inf"], "'-inf' is not finite"),
    (["monitor", "--settle", "nan"], "'--settle': 'nan' is not finite"),
    (["monitor", "--onset", "0"], "'--onset': '0' is out of range"),
    (["monitor", "--gcode", "PNG/x.gcode"], "does not exist"),
    (["history", "--db"], "Option '--db' requires an argument"),
    (["history", "--db", "PNG/h.db"], "is not a folder"),  # a database under a file posing as its folder
    (["history", "--db", "PNG"], "file is not a database"),
    (["report"], "Missing argument 'job'"),
    (["report", "abc"], "'abc' is not a whole number"),
    (["serve", "--port", "70000"], "give a whole number from 1 to 65535"),
    (["serve", "--port", "80.5"], "'80.5' is not a whole number"),
    (["serve", "--images", "PNG"], "is a file"),
    (["demo", "--layers", "0"], "'--layers' / '-n': '0' is out of range"),
    (["demo", "--onset", "inf"], "'--onset': 'inf' is not a whole number"),
    (["demo", "--seed", "1e3"], "'--seed': '1e3' is not a whole number"),
    (["demo", "--frobnicate"], "No such option: --frobnicate"),
    (["calibrate", "--hfov", "0"], "give a finite number from 10 to 170 degrees"),
    (["calibrate", "--square-mm", "-25"], "'--square-mm': '-25' is out of range"),
    (["warp", "PNG", "--z", "nan"], "'--z': 'nan' is not finite"),
    (["warp", "PNG", "--camera", "CAM", "-o", "/"], "is a folder"),
]


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    return make_fixtures(tmp_path_factory.mktemp("fx"))


def _fill(argv, fx):
    sub = {"PNG": str(fx["png"]), "CAM": str(fx["camera"]), "OUT": str(fx["out"])}
    return [re.sub(r"^(PNG|CAM|OUT)", lambda m: sub[m.group(1)], a) for a in argv]


def _run(argv, capsys, monkeypatch, tmp_path):
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))  # where a crash file would go
    code = main(argv)
    cap = capsys.readouterr()
    return code, cap.out, [ln for ln in cap.err.splitlines() if ln.strip()]


VERBS_AT_WRITING = {"calibrate", "warp", "render", "compare", "analyze", "simulate", "evaluate", "monitor",
                    "history", "report", "serve", "demo", "gcode info", "gcode prepare"}


def test_at_least_25_cases_over_every_verb():
    # verbs added later are covered by the generated lines of test_cli_fuzz.py
    verbs = {a[0] if a[0] != "gcode" else f"gcode {a[1]}" for a, _ in USAGE_MISTAKES}
    assert len(USAGE_MISTAKES) >= 25
    assert VERBS_AT_WRITING <= verbs, VERBS_AT_WRITING - verbs
    assert VERBS_AT_WRITING <= {" ".join(p) for p in leaf_commands()}


@pytest.mark.parametrize("argv, phrase", USAGE_MISTAKES, ids=[" ".join(a)[:60] for a, _ in USAGE_MISTAKES])
def test_usage_mistake_is_one_line_and_exit_2(argv, phrase, fx, capsys, monkeypatch, tmp_path):
    code, out, err = _run(_fill(argv, fx), capsys, monkeypatch, tmp_path)
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert phrase in err[0]
    assert "Traceback" not in err[0] and "internal error" not in err[0]
    assert not list(tmp_path.glob("layerwatch-crash-*"))


def test_version_prints_and_exits_0(capsys):
    from layerwatch import __version__

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"layerwatch {__version__}"


def _help(argv, capsys, monkeypatch) -> str:
    monkeypatch.setenv("COLUMNS", "250")
    monkeypatch.setenv("TERMINAL_WIDTH", "250")
    assert main(argv) == 0
    return " ".join(capsys.readouterr().out.split())


def test_help_texts_print_brackets(capsys, monkeypatch):
    assert "Job config TOML ([topview], [render])" in _help(["render", "--help"], capsys, monkeypatch)
    assert "Job config TOML ([topview])" in _help(["simulate", "--help"], capsys, monkeypatch)
    assert "TYPE@LAYER[:SIZE_MM]" in _help(["simulate", "--help"], capsys, monkeypatch)
    text = _help(["compare", "--help"], capsys, monkeypatch)
    assert "Block threshold T_S in [0, 1]. [0<=x<=1]" in text  # the range comes from its Finite parser
    assert "[0<x<=100 px/mm]" in text


def test_user_text_in_an_error_is_not_read_as_markup(capsys, monkeypatch, tmp_path):
    code, _, err = _run(["simulate", "--failure", "[markers]@3"], capsys, monkeypatch, tmp_path)
    assert code == 2 and "unknown failure type '[markers]'" in err[0]


def test_a_bug_is_exit_70_with_a_crash_file(capsys, monkeypatch, tmp_path):
    def broken(*_a, **_k):
        raise ZeroDivisionError("boom")

    monkeypatch.setattr("layerwatch.cli.gcode.read_toolpath", broken)
    code, _, err = _run(["gcode", "info", EX], capsys, monkeypatch, tmp_path)
    assert code == 70 and len(err) == 1 and err[0].startswith("internal error: ZeroDivisionError: boom")
    crash = list(tmp_path.glob("layerwatch-crash-*.txt"))
    assert len(crash) == 1 and "Traceback" in crash[0].read_text() and str(crash[0]) in err[0]


def test_a_path_that_fails_only_when_used_is_exit_2(capsys, monkeypatch, tmp_path):
    # /proc takes no new folder even from root, who passes the edge's permission check
    code, _, err = _run(["history", "--db", "/proc/layerwatch-missing/h.db"], capsys, monkeypatch, tmp_path)
    assert code == 2 and len(err) == 1 and err[0].startswith("error: ") and "/proc" in err[0]


def test_analyze_exits_1_when_nothing_was_analysed(fx, capsys, monkeypatch, tmp_path):
    # a 60x60 photo does not fit the 1280x720 camera model: a warning, no layer analysed
    code, _, err = _run(["analyze", str(fx["png"]), "--gcode", EX, "--camera", str(fx["camera"]),
                         "-o", str(tmp_path / "res")], capsys, monkeypatch, tmp_path)
    assert code == 1
    assert err == ["error: no layer was analysed; see the warnings above."]


def test_every_numeric_parameter_has_a_finite_parser():
    numeric = [(" ".join(path), p.name) for path, cmd in leaf_commands().items() for p in cmd.params
               if getattr(getattr(p, "type_descriptor", None), "annotation", None) in (int, float)]
    assert len(numeric) >= 25
    missing = [(v, n) for v, n in numeric for path, cmd in leaf_commands().items() if " ".join(path) == v
               for p in cmd.params if p.name == n and finite_of(p) is None]
    assert not missing, f"declare these with parser=Finite(lo, hi): {missing}"


@pytest.mark.parametrize("text, parser, value", [
    ("5", Finite(0, 50), 5.0), (" 12 ", Finite(1, 100, integer=True), 12), ("0", Finite(0, 1), 0.0),
    ("-3.5e1", Finite(-100, 0), -35.0), ("+7", Finite(integer=True), 7), (2.5, Finite(0, 5), 2.5),
])
def test_finite_accepts(text, parser, value):
    got = parser(text)
    assert got == value and type(got) is type(value)


@pytest.mark.parametrize("text, parser, words", [
    ("nan", Finite(), "not finite"), ("-inf", Finite(), "not finite"), ("1e999", Finite(), "not finite"),
    ("abc", Finite(), "not a number"), ("", Finite(), "not a number"), ("1_000", Finite(), "not a number"),
    ("0", Finite(0, lo_open=True), "out of range; give a finite number > 0"),
    ("50.0001", Finite(0, 50, unit="mm"), "give a finite number from 0 to 50 mm"),
    ("1.5", Finite(integer=True), "not a whole number"), ("1e3", Finite(integer=True), "not a whole number"),
    ("0x10", Finite(integer=True), "not a whole number"), (True, Finite(), "not a number"),
    (float("nan"), Finite(0, 1), "not finite"),
])
def test_finite_refuses(text, parser, words):
    with pytest.raises(typer.BadParameter, match=re.escape(words)):
        parser(text)


def test_writable(tmp_path):
    f = tmp_path / "f.txt"
    f.write_text("x")
    assert Writable()(str(tmp_path / "new.png")) == tmp_path / "new.png"
    assert Writable(folder=True)(str(tmp_path / "a" / "b")) == tmp_path / "a" / "b"
    assert Writable(make_parents=True)(str(tmp_path / "a" / "h.db")) == tmp_path / "a" / "h.db"
    for parser, value, words in [(Writable(), tmp_path, "is a folder"), (Writable(folder=True), f, "is a file"),
                                 (Writable(), tmp_path / "a" / "x.png", "does not exist"),
                                 (Writable(folder=True), f / "sub", "is not a folder"), (Writable(), "", "empty")]:
        with pytest.raises(typer.BadParameter, match=words):
            parser(str(value))


def _script() -> str | None:
    beside = Path(sys.executable).with_name("layerwatch")
    return str(beside) if beside.is_file() else shutil.which("layerwatch")


@pytest.mark.slow
@pytest.mark.skipif(_script() is None, reason="the layerwatch script is not installed")
@pytest.mark.parametrize("argv", [["--version"], ["renderr"], ["gcode", "prepare", EX, "--every", "nan"], []])
def test_python_m_and_the_script_behave_the_same(argv):
    src = str(Path(__file__).resolve().parents[2] / "src")
    env = {**os.environ, "PYTHONPATH": src, "COLUMNS": "120"}
    # both at once (each is a cold start: imports, not waits)
    procs = [subprocess.Popen(cmd + argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for cmd in ([sys.executable, "-m", "layerwatch"], [_script()])]
    try:
        (a_out, a_err), (b_out, b_err) = (p.communicate(timeout=60) for p in procs)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(15)  # reaped here: else its ResourceWarning fails whichever test the GC runs in
    a, b = procs
    assert (a.returncode, a_out, a_err) == (b.returncode, b_out, b_err)
    assert a.returncode in (0, 2) and "Traceback" not in a_err
    if argv and argv[0] != "--version":
        assert len(a_err.strip().splitlines()) == 1
