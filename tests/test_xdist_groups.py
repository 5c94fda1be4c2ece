"""Under xdist, an ``xdist_group`` stays on one worker and an ``exclusive`` test runs alone (``tests/xdist_groups.py``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("xdist")

GROUPED = """
import os
import pytest

pytestmark = pytest.mark.xdist_group("servers")


@pytest.mark.parametrize("i", range(6))
def test_grouped(i):
    with open("workers.txt", "a") as f:
        f.write(f"grouped {os.environ['PYTEST_XDIST_WORKER']}\\n")
"""
LOOSE = """
import os
import pytest


@pytest.mark.parametrize("i", range(6))
def test_loose(i):
    with open("workers.txt", "a") as f:
        f.write(f"loose {os.environ['PYTEST_XDIST_WORKER']}\\n")
"""


TIMED = """
import time
import pytest


def _timed(kind, seconds):
    t0 = time.monotonic()
    time.sleep(seconds)
    with open("times.txt", "a") as f:
        f.write(f"{kind} {t0} {time.monotonic()}\\n")


@pytest.mark.parametrize("i", range(6))
def test_before(i):
    _timed("loose", 0.3)


@pytest.mark.exclusive
def test_alone():
    _timed("alone", 1.5)


@pytest.mark.parametrize("i", range(6))
def test_after(i):
    _timed("loose", 0.3)
"""


def _pytest(folder: Path, *files: tuple[str, str]) -> subprocess.CompletedProcess:
    for name, text in files:
        (folder / name).write_text(text)
    (folder / "pytest.ini").write_text("[pytest]\nmarkers =\n    exclusive: runs alone\n")
    env = dict(os.environ, PYTEST_DISABLE_PLUGIN_AUTOLOAD="1",
               PYTHONPATH=os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]))
    run = subprocess.run([sys.executable, "-m", "pytest", "-p", "xdist", "-p", "xdist_groups", "-p", "no:cacheprovider",
                          "-n", "2", "--dist", "loadgroup", "-v"], cwd=folder, env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return run


def test_an_exclusive_test_runs_while_no_other_test_runs(tmp_path):
    _pytest(tmp_path, ("test_timed.py", TIMED))
    rows = [line.split() for line in (tmp_path / "times.txt").read_text().splitlines()]
    (alone,) = [(float(a), float(b)) for kind, a, b in rows if kind == "alone"]
    loose = [(float(a), float(b)) for kind, a, b in rows if kind == "loose"]
    assert len(loose) == 12
    assert not [t for t in loose if t[0] < alone[1] and alone[0] < t[1]], (alone, loose)  # no overlap


def test_a_group_runs_on_one_worker(tmp_path):
    run = _pytest(tmp_path, ("test_grouped.py", GROUPED), ("test_loose.py", LOOSE))
    # xdist tells its scheduler the group by this suffix of the node id: without the shim, pytest 9.2 loses it
    assert len(re.findall(r"PASSED test_grouped\.py::test_grouped\[\d\]@servers", run.stdout)) == 6, run.stdout[-3000:]
    rows = [line.split() for line in (tmp_path / "workers.txt").read_text().splitlines()]
    grouped = {w for kind, w in rows if kind == "grouped"}
    assert len(rows) == 12 and len(grouped) == 1, rows
