"""A command line loads only its verb's module (``layerwatch.cli.VERBS``)."""

from __future__ import annotations

import subprocess
import sys

import typer

from layerwatch import cli
from layerwatch.examples import PART_GCODE


def test_verb_table_matches_the_full_app():
    group = typer.main.get_command(cli.app)  # every verb registered
    assert set(group.commands) == set(cli.VERBS)
    for verb, module in cli.VERBS.items():
        callback = group.commands[verb].callback
        if callback is None:  # a group (gcode, config): its sub-verbs' callbacks live in the module
            callback = next(iter(group.commands[verb].commands.values())).callback
        assert callback.__module__ == f"layerwatch.cli.{module}", (verb, callback.__module__)


def test_gcode_info_does_not_load_the_renderer_opencv_or_the_dashboard():
    code = (
        "import sys, io, contextlib\n"
        "from layerwatch.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        f"    assert main(['gcode', 'info', {str(PART_GCODE)!r}]) == 0\n"
        "heavy = [m for m in ('cv2', 'fastapi', 'matplotlib', 'trimesh', 'layerwatch.render', 'layerwatch.web',"
        " 'layerwatch.pipeline', 'layerwatch.analysis') if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"loaded by `gcode info`: {out.stdout.strip()}"


def test_history_works_without_loading_the_web_extra(tmp_path):
    """``history`` and ``report`` need no FastAPI: only ``serve`` imports the dashboard app (optional ``web`` extra)."""
    code = (
        "import sys, io, contextlib\n"
        "from layerwatch.cli import main\n"
        "from layerwatch.storage.history import History\n"
        f"History({str(tmp_path / 'h.db')!r}).close()\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        f"    assert main(['history', '--db', {str(tmp_path / 'h.db')!r}]) == 0\n"
        "print(','.join(m for m in ('fastapi', 'starlette', 'uvicorn', 'layerwatch.web.app') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"loaded by `history`: {out.stdout.strip()}"
