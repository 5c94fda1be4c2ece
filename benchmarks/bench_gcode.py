"""G-code parse speed and memory: layerwatch vs the `gcodeparser` PyPI package.

Run: ``.venv/bin/python -m pytest benchmarks/bench_gcode.py -s``

Targets (issue 4): >= 30 MB/s on one core, >= 10x gcodeparser on the same
data in the same run, peak memory <= 3x the arrays kept. gcodeparser is run
on a smaller slice of the same concatenated file (it is slow); both rates are
MB/s over the bytes each one parsed.
"""

from __future__ import annotations

import os
import time
import tracemalloc
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("LAYERWATCH_SHARED_DATA", REPO.parent / "shared" / "data")) / "gcode"
SOURCE = "cura-2.3.1_reprap.gcode"  # plain G0/G1 Marlin-style file (the commonest dialect)
TARGET_MB = 30


def _big_file(tmp: Path, name: str = SOURCE, target_mb: int = TARGET_MB) -> Path:
    src = (SHARED / name).read_bytes()
    reps = max(1, int(target_mb * 1e6 // len(src)))
    out = tmp / f"big_{name}"
    out.write_bytes(src * reps)
    return out


def _best(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


@pytest.mark.skipif(not (SHARED / SOURCE).is_file(), reason="shared data absent")
def test_parse_speed_vs_gcodeparser(tmp_path):
    from gcodeparser import parse_gcode_lines

    from layerwatch.gcode import read_toolpath

    big = _big_file(tmp_path)
    data = big.read_bytes()
    mb = len(data) / 1e6
    read_toolpath(data[:200_000])  # JIT warm-up (cached on disk after the first run)
    t_lw = _best(lambda: read_toolpath(data))
    tp = read_toolpath(data)
    rate_lw = mb / t_lw

    # gcodeparser on a ~2 MB slice of the same bytes, cut at a line end
    cut = data.rfind(b"\n", 0, 2_000_000) + 1
    text = data[:cut].decode("latin-1")
    t_gp = _best(lambda: sum(1 for _ in parse_gcode_lines(text)), repeat=1)
    rate_gp = cut / 1e6 / t_gp
    # layerwatch on the very same slice too (rates should agree with the big file)
    t_lw_small = _best(lambda: read_toolpath(data[:cut]))

    tracemalloc.start()
    tp2 = read_toolpath(data)
    _cur, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    kept = tp2.nbytes()

    print()
    print(f"file: {SOURCE} x{len(data) // (SHARED / SOURCE).stat().st_size} = {mb:.1f} MB, "
          f"{tp.n_segments} segments, {tp.n_layers} layers ({tp.detection})")
    print(f"layerwatch  : {rate_lw:8.1f} MB/s  ({t_lw:.3f} s for {mb:.1f} MB; "
          f"{cut / 1e6 / t_lw_small:.1f} MB/s on the {cut / 1e6:.1f} MB slice)")
    print(f"gcodeparser : {rate_gp:8.2f} MB/s  ({t_gp:.3f} s for {cut / 1e6:.1f} MB slice)")
    print(f"speed ratio : {rate_lw / rate_gp:8.1f} x  (target >= 10 x; absolute target >= 30 MB/s)")
    # tracemalloc sees NumPy and numba-NRT buffers alike; the input bytes were read before it started
    print(f"memory      : tracemalloc peak {peak / 1e6:.1f} MB vs arrays kept "
          f"{kept / 1e6:.1f} MB -> {peak / kept:.2f} x  (target <= 3 x)")
    assert tp.n_segments > 0


@pytest.mark.skipif(
    not (SHARED / "prusaslicer-2.7.4_arc-fitting_zhop.gcode").is_file(), reason="shared data absent"
)
def test_parse_speed_arc_fitted_prusaslicer(tmp_path):
    """PrusaSlicer with arc fitting (G2/G3 linearised at 0.01 mm) and Z-hops, ~20 MB."""
    from gcodeparser import parse_gcode_lines

    from layerwatch.gcode import read_toolpath

    data = _big_file(tmp_path, "prusaslicer-2.7.4_arc-fitting_zhop.gcode", 20).read_bytes()
    read_toolpath(data[:100_000])
    t = _best(lambda: read_toolpath(data))
    tp = read_toolpath(data)
    cut = data.rfind(b"\n", 0, 1_000_000) + 1
    try:
        t0 = time.perf_counter()
        sum(1 for _ in parse_gcode_lines(data[:cut].decode("latin-1")))
        gp = f"{cut / 1e6 / (time.perf_counter() - t0):.2f} MB/s"
    except Exception as exc:  # gcodeparser cannot lex some PrusaSlicer lines
        gp = f"fails ({type(exc).__name__}: {exc})"
    print()
    print(f"arc-fitted PrusaSlicer: layerwatch {len(data) / 1e6 / t:.1f} MB/s "
          f"({tp.n_segments} segments after arc linearisation); gcodeparser: {gp}")
