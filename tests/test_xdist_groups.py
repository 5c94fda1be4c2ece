"""`--dist loadgroup` keeps an ``xdist_group`` on one worker (with the shim of ``tests/xdist_groups.py``)."""

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


def test_a_group_runs_on_one_worker(tmp_path):
    (tmp_path / "test_grouped.py").write_text(GROUPED)
    (tmp_path / "test_loose.py").write_text(LOOSE)
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    env = dict(os.environ, PYTEST_DISABLE_PLUGIN_AUTOLOAD="1",
               PYTHONPATH=os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]))
    run = subprocess.run([sys.executable, "-m", "pytest", "-p", "xdist", "-p", "xdist_groups", "-p", "no:cacheprovider",
                          "-n", "2", "--dist", "loadgroup", "-v"], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    # xdist tells its scheduler the group by this suffix of the node id: without the shim, pytest 9.2 loses it
    assert len(re.findall(r"PASSED test_grouped\.py::test_grouped\[\d\]@servers", run.stdout)) == 6, run.stdout[-3000:]
    rows = [line.split() for line in (tmp_path / "workers.txt").read_text().splitlines()]
    grouped = {w for kind, w in rows if kind == "grouped"}
    assert len(rows) == 12 and len(grouped) == 1, rows
