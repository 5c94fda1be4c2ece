"""G-code reader speed (issue 20): this reader vs the reader of BASELINE_COMMIT vs `gcodeparser`,
all in the same process on the same bytes, plus `layerwatch gcode info` from cold.

Run: ``.venv/bin/python -m pytest benchmarks/bench_gcode_reader.py -s -p no:cacheprovider``

Targets: warm parsing >= 200 MB/s on one core; ``gcode info`` on a 20 MB file <= 0.5 s cold.
The baseline is the ``layerwatch.gcode`` package as it was at BASELINE_COMMIT, extracted with
``git show`` into a temporary package (skipped where the checkout has no git history).
"""

from __future__ import annotations

import importlib
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("LAYERWATCH_SHARED_DATA", REPO.parent / "shared" / "data")) / "gcode"
SOURCE = "cura-2.3.1_reprap.gcode"  # plain Marlin-style Cura output (gcodeparser reads it), repeated to ~20 MB
TARGET_MB = 20
BASELINE_COMMIT = "0c32081"  # main before issue 20
BASELINE_PKG = "lw_gcode_baseline"


def _best(fn, repeat: int = 3, clock=time.process_time) -> float:
    """Best of ``repeat`` runs. In-process parsing is timed in CPU seconds of this process
    (one core; steadier than wall time on a shared machine); subprocesses in wall seconds."""
    best = float("inf")
    for _ in range(repeat):
        t0 = clock()
        fn()
        best = min(best, clock() - t0)
    return best


def _baseline_reader(tmp: Path):
    """The ``reader`` module of BASELINE_COMMIT, imported as a separate package, or None."""
    if shutil.which("git") is None:
        return None
    pkg = tmp / BASELINE_PKG
    pkg.mkdir()
    names = subprocess.run(["git", "-C", str(REPO), "ls-tree", "--name-only", BASELINE_COMMIT,
                            "src/layerwatch/gcode/"], capture_output=True, text=True)
    if names.returncode != 0:
        return None
    for path in names.stdout.split():
        if path.endswith(".py"):
            src = subprocess.run(["git", "-C", str(REPO), "show", f"{BASELINE_COMMIT}:{path}"],
                                 capture_output=True, text=True, check=True).stdout
            (pkg / Path(path).name).write_text(src.replace("layerwatch.gcode", BASELINE_PKG))
    sys.path.insert(0, str(tmp))
    return importlib.import_module(f"{BASELINE_PKG}.reader")


@pytest.mark.skipif(not (SHARED / SOURCE).is_file(), reason="shared data absent")
def test_reader_speed(tmp_path):
    from gcodeparser import parse_gcode_lines

    from layerwatch.gcode import read_toolpath
    from layerwatch.gcode.reader import kernel_outputs

    src = (SHARED / SOURCE).read_bytes()
    data = src * max(1, int(TARGET_MB * 1e6 // len(src)))
    big = tmp_path / "big.gcode"
    big.write_bytes(data)
    mb = len(data) / 1e6
    read_toolpath(data[:200_000])  # load the compiled kernels (cached on disk)
    t_new = _best(lambda: read_toolpath(data))
    t_kernel = _best(lambda: kernel_outputs(data))
    old = _baseline_reader(tmp_path)
    t_old = None
    if old is not None:
        old.read_toolpath(data[:200_000])
        t_old = _best(lambda: old.read_toolpath(data))
        t_old_kernel = _best(lambda: old.kernel_outputs(data))
    cut = data.rfind(b"\n", 0, 2_000_000) + 1
    text = data[:cut].decode("latin-1")
    t_gp = _best(lambda: sum(1 for _ in parse_gcode_lines(text)), repeat=1)
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    cli = [sys.executable, "-c", "import sys; from layerwatch.cli import main; sys.exit(main(sys.argv[1:]))",
           "gcode", "info", str(big)]
    subprocess.run(cli, capture_output=True, env=env)  # compile/stamp once
    wall = time.perf_counter
    t_cold = _best(lambda: subprocess.run(cli, capture_output=True, env=env, check=True), repeat=2, clock=wall)
    t_py = _best(lambda: subprocess.run([sys.executable, "-c", "pass"], check=True), repeat=2, clock=wall)

    print()
    print(f"file: {SOURCE} x{len(data) // len(src)} = {mb:.1f} MB")
    print("rates in MB per CPU-second of one core:")
    print(f"this reader     : {mb / t_new:7.1f} MB/s  ({t_new:.3f} s; kernel alone {mb / t_kernel:.1f} MB/s)")
    if t_old is not None:
        print(f"baseline {BASELINE_COMMIT}: {mb / t_old:7.1f} MB/s  ({t_old:.3f} s; kernel alone "
              f"{mb / t_old_kernel:.1f} MB/s)  -> ratio {t_old / t_new:.2f} x, kernels {t_old_kernel / t_kernel:.2f} x")
    print(f"gcodeparser     : {cut / 1e6 / t_gp:7.2f} MB/s  ({t_gp:.3f} s on a {cut / 1e6:.1f} MB slice)"
          f"  -> ratio {(mb / t_new) / (cut / 1e6 / t_gp):.1f} x")
    print(f"gcode info cold : {t_cold:.2f} s wall for {mb:.1f} MB (bare python start {t_py:.2f} s); target <= 0.5 s")
    print("warm target >= 200 MB/s:", "met" if mb / t_new >= 200 else "NOT met")
