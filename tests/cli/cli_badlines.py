"""Deterministic generator of bad ``layerwatch`` command lines, and an in-process runner.

The generator reads the verbs and their parameters from the app itself (the click command
tree typer builds), so a verb or option added later is fuzzed without touching this file.
Each generated line carries at least one mistake a user can make: an unknown option, a typo
in a verb, a missing required parameter or value, a number that is not finite, not a number
or out of any sensible range, an unknown choice, an extra argument, or a path that is not
the file it should be.

:func:`run_line` calls :func:`layerwatch.cli.main` with stdout/stderr captured. Long-running
work (the monitor loop, the dashboard server, evaluation, demo, simulation,
rendering) is replaced by a function raising :class:`ReachedWork`: a bad line that gets that far
was accepted, which is reported as the outcome ``"work"`` instead of an exit code.
"""

from __future__ import annotations

import contextlib
import io
import random
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import typer

from layerwatch.cli import app, main

__all__ = ["ReachedWork", "Outcome", "leaf_commands", "bad_lines", "run_line", "run_all", "make_fixtures"]

# Values no numeric option of layerwatch accepts (not a number, not finite, absurd).
BAD_FLOATS = ("nan", "NaN", "inf", "-inf", "1e999", "-1e999", "abc", "", "1,5", "0x1p3", "1e12", "-1e12")
BAD_INTS = ("nan", "inf", "1.5", "1e3", "abc", "", "-99999999", "99999999999", "0b11")
BAD_CHOICES = ("bogus", "[markers]", "", " ")
# Paths that cannot be created even by root (/proc refuses new entries; /dev/null is no folder).
BAD_PATHS = ("/proc/layerwatch-missing/file", ".", "/dev/null", "")
WRONG_FILES = ("junk", "empty", "png", "gcode", "toml_bad")  # fixtures that are the wrong kind of file
BAD_OUTPUTS = ("/proc/layerwatch-missing/out", "/dev/null/out")
FILE_OUTPUTS = {"output", "json_out"}
DIR_OUTPUTS = {"out", "outdir", "cache"}
DIR_INPUTS = {"images"}
# Options whose text is parsed by the command: malformed or non-finite specs.
SPEC_OPTIONS = {
    "--layers": ("abc", "5:1:0", "-99999", "1e3", "nan", "1:2:3:4"),
    "--park": ("nan,nan", "inf,0", "1", "a,b", "1e999,5"),
    "--volume": ("nan,nan,nan", "-1,-1,-1", "1,2", "inf,200,200"),
    "--failure": ("spaghetti@x", "bogus@3", "spaghetti@-1", "spaghetti@3:nan", "spaghetti@3:inf", "@"),
    "--board-size": ("0x0", "-3x4", "axb", "9x6x2", "99999x99999"),
}
CHOICE_OPTIONS = {"--profile", "--metric", "--backend", "--failure", "--printer", "--camera", "--scheduler"}


class ReachedWork(BaseException):  # noqa: N818 - a signal, not an error
    """Raised by the stand-ins of long-running work: the command line was accepted."""


@dataclass(frozen=True)
class Outcome:
    """What one command line did: exit code (or ``"work"``) and its captured stderr."""

    argv: tuple[str, ...]
    code: int | str
    stderr: str

    @property
    def traceback(self) -> bool:
        return "Traceback (most recent call last)" in self.stderr

    @property
    def stderr_lines(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines() if ln.strip()]


def leaf_commands() -> dict[tuple[str, ...], object]:
    """Every runnable command as ``{("gcode", "prepare"): click_command, ...}``."""
    out: dict[tuple[str, ...], object] = {}

    def walk(cmd, path):
        subs = getattr(cmd, "commands", None)
        if subs:
            for name, sub in subs.items():
                walk(sub, (*path, name))
        else:
            out[path] = cmd

    walk(typer.main.get_command(app), ())
    return out


def _annotation(param):
    return getattr(getattr(param, "type_descriptor", None), "annotation", None)


def _is_flag(param) -> bool:
    return bool(getattr(param, "is_flag", False))


def make_fixtures(root: Path) -> dict[str, Path]:
    """Small valid input files under ``root``: G-code, images, camera model, job config."""
    import cv2
    import numpy as np

    from layerwatch.examples import PART_CONFIG, PART_GCODE
    from layerwatch.geometry.topview import TopView
    from layerwatch.simulate import default_camera

    (root / "out").mkdir(parents=True, exist_ok=True)
    (root / "junk.bin").write_bytes(bytes(range(256)) * 40)
    (root / "empty.txt").write_bytes(b"")
    (root / "bad.toml").write_text("[topview]\npx_per_mm = 'many'\n[[[\n")
    png = root / "img.png"
    cv2.imwrite(str(png), np.full((60, 60, 3), 128, np.uint8))
    cam = root / "camera.toml"
    default_camera(TopView(6.67, 90, 90, (110, 100))).save(cam)
    return {"gcode": PART_GCODE, "png": png, "camera": cam, "config": PART_CONFIG, "out": root / "out",
            "junk": root / "junk.bin", "empty": root / "empty.txt", "toml_bad": root / "bad.toml"}


def _valid_value(param, fx: dict[str, Path]) -> str:
    """A plausible valid value for ``param`` (files from ``fx``)."""
    name = param.name or ""
    ann = _annotation(param)
    if ann in (int, float):
        return "1"
    if "camera" in name and ann is not str:
        return str(fx["camera"])
    if name in {"photo", "photo_top", "reference", "mask", "photos", "markers", "bed_photo"}:
        return str(fx["png"])
    if name in {"config"}:
        return str(fx["config"])
    if name in {"output", "out", "outdir", "json_out", "cache", "db", "images"}:
        return str(fx["out"] / name)
    if name == "printer":
        return "virtual"
    return str(fx["gcode"])


# options that let a line reach past the command's first check (values: fixture names)
BASE_EXTRAS = {("calibrate",): ("--board", "png"), ("warp",): ("--camera", "camera")}


def _extras(path, fx, skip=()) -> list[str]:
    extra = BASE_EXTRAS.get(tuple(path), ())
    if set(extra) & set(skip):
        return []
    return [str(fx.get(t, t)) for t in extra]


def _argv(path, cmd, fx, param=None, value: str | None = None, drop=None) -> list[str]:
    """The command with every required parameter valid, ``param`` set to ``value``, ``drop`` left out."""
    argv = list(path) + _extras(path, fx, skip=param.opts if param is not None else ())
    for q in cmd.params:
        if q is drop or not (q.required or q is param):
            continue
        v = value if q is param else _valid_value(q, fx)
        argv += [v] if q.param_type_name == "argument" else [q.opts[0], v]
    return argv


def _bad_paths(param, fx) -> tuple[str, ...]:
    """Values that are wrong for this path parameter (by its role: input file or folder, output)."""
    name = param.name or ""
    if name in FILE_OUTPUTS:  # a file to write: where no file can be
        return BAD_OUTPUTS + ("/",)
    if name in DIR_OUTPUTS:  # a folder to write into: under a file, or an existing file
        # (not /proc/...: root passes the edge check there and a long run would only fail at its end)
        return ("/dev/null/out", str(fx["png"] / "sub"), str(fx["png"]))
    if name in DIR_INPUTS:
        return ("/proc/layerwatch-missing/dir", str(fx["png"]))
    wrong = [k for k in WRONG_FILES if str(fx[k]) != _valid_value(param, fx)]
    if name in {"config", "db", "history"}:  # an empty file is a valid (empty) config or database
        wrong.remove("empty")
    return BAD_PATHS + tuple(str(fx[k]) for k in wrong)


def _typo(word: str, rng: random.Random) -> str:
    i = rng.randrange(len(word))
    kind = rng.choice(("double", "drop", "swap", "upper"))
    if kind == "double" or len(word) < 3:
        return word[: i + 1] + word[i] + word[i + 1:]
    if kind == "drop":
        return word[:i] + word[i + 1:]
    if kind == "swap" and i < len(word) - 1:
        return word[:i] + word[i + 1] + word[i] + word[i + 2:]
    return word.upper()


def _lines_for(path, cmd, fx, rng: random.Random) -> list[list[str]]:
    base = _argv(path, cmd, fx)
    n = len(path)
    out = [
        base + ["--bogus"],
        base + ["--bogus=1"],
        [*path, "--no-such-option", "x"],
        base + ["extra-argument"] * 4,
        base + ["-Z"],  # unknown short option
    ]
    for k in range(n):  # typo in each level of the verb
        bad = list(path)
        bad[k] = _typo(path[k], rng)
        if bad[k] != path[k]:
            out.append(bad + base[n:])
    out += [_argv(path, cmd, fx, drop=p) for p in cmd.params if p.required]  # each required one left out
    for p in cmd.params:  # every input path: missing, a folder, a device, empty, the wrong kind of file
        if _annotation(p) is not Path or _is_flag(p):
            continue
        values = _bad_paths(p, fx)
        for v in values:
            out.append(_argv(path, cmd, fx, p, v))
    for p in cmd.params:
        if p.param_type_name != "option" or _is_flag(p) or p.name == "help":
            continue
        opt = p.opts[0]
        out.append(base + [opt])  # option without its value
        ann = _annotation(p)
        if ann is float:
            out += [base + [opt, v] for v in rng.sample(BAD_FLOATS, 6)]
        elif ann is int:
            out += [base + [opt, v] for v in rng.sample(BAD_INTS, 5)]
        elif ann is not int and set(p.opts) & set(SPEC_OPTIONS):
            out += [base + [opt, v] for v in SPEC_OPTIONS[next(o for o in p.opts if o in SPEC_OPTIONS)]]
        elif set(p.opts) & CHOICE_OPTIONS:
            out += [base + [opt, v] for v in BAD_CHOICES[:2]]
    return out


def bad_lines(root: Path, seed: int = 19) -> list[list[str]]:
    """Every generated bad command line over every verb, with its input files made under ``root``.

    The lines depend only on ``seed`` and ``root``; run them with ``cwd=root``.
    """
    fx = make_fixtures(root / "fixtures")
    rng = random.Random(seed)
    lines = [["--bogus"], ["renderr"], ["--version", "--bogus"], ["gcode", "--bogus"], ["gcodee", "info"]]
    for path, cmd in sorted(leaf_commands().items()):
        lines += _lines_for(path, cmd, fx, rng)
    return lines


_HEAVY = (
    "layerwatch.monitor.service.Monitor.run",
    "layerwatch.evaluate.harness.run_evaluation",
    "layerwatch.cli.pipeline.run_evaluation",  # imported by name at the verb module's top
    "layerwatch.evaluate.demo.run_demo",
    "layerwatch.cli.demo.run_demo",  # imported by name at the verb module's top
    "layerwatch.simulate.simulate_print",
    "layerwatch.render.backend.render_layers",
    "layerwatch.cli.render.render_layers",  # imported by name at the verb module's top
    "uvicorn.run",
)


def _reached(*_a, **_k):
    raise ReachedWork


def run_line(argv: list[str], cwd: Path | None = None) -> Outcome:
    """Run ``layerwatch ARGV`` in-process; long-running work raises :class:`ReachedWork`."""
    import os

    err, out = io.StringIO(), io.StringIO()
    old = os.getcwd()
    with contextlib.ExitStack() as stack:
        for target in _HEAVY:
            stack.enter_context(mock.patch(target, _reached))
        stack.enter_context(contextlib.redirect_stderr(err))
        stack.enter_context(contextlib.redirect_stdout(out))
        if cwd is not None:
            os.chdir(cwd)
            stack.enter_context(mock.patch("tempfile.tempdir", str(cwd)))  # crash files stay in cwd
        try:
            code: int | str = main(list(argv))
        except ReachedWork:
            code = "work"
        except SystemExit as exc:  # main() must not exit; count it as what the shell would see
            code = f"SystemExit({exc.code})"
        except BaseException as exc:  # noqa: BLE001 - anything escaping main() is a finding
            code = f"raised {type(exc).__name__}"
            err.write(f"Traceback (most recent call last): {exc!r}\n")
        finally:
            os.chdir(old)
    return Outcome(tuple(argv), code, err.getvalue())


def run_all(lines: list[list[str]], cwd: Path) -> tuple[list[Outcome], Counter]:
    """Run every line; return the outcomes and the histogram of exit codes."""
    results = [run_line(a, cwd) for a in lines]
    return results, Counter(str(r.code) for r in results)


if __name__ == "__main__":  # python tests/cli/cli_badlines.py: print the histogram and the findings
    import sys
    import tempfile
    import time

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        lines = bad_lines(Path(d))
        results, hist = run_all(lines, Path(d))
    print(f"{len(lines)} bad command lines in {time.perf_counter() - t0:.1f} s: {dict(sorted(hist.items()))}")
    verbose = "-v" in sys.argv
    for r in results:
        multi = r.code == 2 and len(r.stderr_lines) != 1
        if r.code not in (1, 2) or r.traceback or multi or verbose:
            print(r.code, "multi-line" if multi else "", " ".join(map(repr, r.argv)), "->", r.stderr.strip()[:300])
