"""Speed of the print simulator: incremental frames vs re-simulating each frame from scratch.

Run: ``python benchmarks/bench_simulate.py`` or ``pytest benchmarks/bench_simulate.py -s``.
Uses the bundled example part (``read_toolpath``; falls back to the synthetic
``box_part`` when the parser is absent), a 1280 x 720 camera at 45 degrees,
one thread, one failure of each kind in turn. Target (issue 8): <= 150 ms per
simulated frame so that 200 layers simulate + evaluate in <= 2 min.
Baseline: ``simulate_layer`` per frame (height field rebuilt from layer 0).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import time  # noqa: E402

from layerwatch.geometry.topview import TopView  # noqa: E402
from layerwatch.simulate import (  # noqa: E402
    FAILURE_TYPES,
    Failure,
    default_camera,
    simulate_layer,
    simulate_print,
)


def _toolpath():
    try:
        from layerwatch.examples import PART_GCODE
        from layerwatch.gcode import read_toolpath

        return read_toolpath(PART_GCODE), TopView(6.67, 90, 90, (110.0, 100.0))
    except ImportError:
        from layerwatch.simulate.parts import box_part

        return box_part(size_mm=40, height_mm=10, layer_h=0.3), TopView(6.67, 90, 90, (0, 0))


def run() -> dict:
    tp, tv = _toolpath()
    cam = default_camera(tv)
    simulate_layer(tp, 1, cam, tv, [Failure("spaghetti", 0)])  # JIT warm-up
    n = tp.n_layers
    frames = 0
    t = time.perf_counter()
    for k, kind in enumerate(FAILURE_TYPES):
        f = Failure(kind, onset=n // 2, size_mm=8.0 if kind not in ("layer_shift", "detachment") else 3.0,
                    seed=k)
        for _ in simulate_print(tp, cam, tv, [f], seed=k):
            frames += 1
    inc = (time.perf_counter() - t) / frames * 1000
    idx = list(range(0, n, max(n // 6, 1)))
    t = time.perf_counter()
    for i in idx:
        simulate_layer(tp, i, cam, tv, [Failure("foreign_body", onset=0)], seed=1)
    base = (time.perf_counter() - t) / len(idx) * 1000
    out = {"layers": n, "frames": frames, "ms_per_frame": inc, "baseline_ms_per_frame": base,
           "speedup": base / inc}
    print(f"simulator: {n} layers, {frames} frames at 1280x720: {inc:.1f} ms/frame incremental "
          f"(target <= 150); from-scratch baseline {base:.1f} ms/frame; ratio {base / inc:.1f}x")
    return out


def test_bench_simulate():
    res = run()
    assert res["frames"] == 6 * res["layers"]


if __name__ == "__main__":
    run()
