"""Speed of the fast reference renderer (issue 6: <= 50 ms per 600x600 layer of 20,000 segments).

Run: ``python benchmarks/bench_render.py`` or ``pytest benchmarks/bench_render.py -s``.
Layer: synthetic dense 45-degree infill of 20,000 short segments, 0.45 mm
beads, 90 x 90 mm at 6.67 px/mm (600 x 600 px), one core.

Timed in the same process:

* ``render_layer`` from scratch (rasterise + shade), median of several runs;
* incremental per-layer time over a stack of such layers (``render_stack``);
* the camera-view reference (:mod:`layerwatch.render.camera_view`, the
  pipeline's default) against the top view of the same layer (its extra cost);
* baseline 1: naive per-segment ``cv2.line`` (thick, anti-aliased) + ``cv2.circle``
  caps drawn from Python, no shading;
* baseline 2 (when ``blender`` is on PATH and ``LAYERWATCH_BENCH_BLENDER`` is
  not ``0``): a Blender Cycles render of the same layer at 600 x 600,
  ``LAYERWATCH_BENCH_SAMPLES`` samples (default 16), one thread. Target ratio >= 1000x.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import shutil  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from layerwatch.gcode.toolpath import Toolpath  # noqa: E402
from layerwatch.geometry.topview import TopView  # noqa: E402
from layerwatch.render.fast import StackRenderer, render_stack  # noqa: E402
from layerwatch.render.settings import RenderSettings  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "render"))  # test-only part generators
from render_parts import dense_layer  # noqa: E402

cv2.setNumThreads(1)
TV = TopView(6.67, 90.0, 90.0, (0.0, 0.0))


def naive_cv2(tp: Toolpath, tv: TopView) -> np.ndarray:
    """Baseline: one cv2.line + two cv2.circle calls per segment (Python loop)."""
    img = np.zeros(tv.shape, np.uint8)
    p0 = np.round(tv.to_px(tp.start) * 16).astype(int)
    p1 = np.round(tv.to_px(tp.end) * 16).astype(int)
    th = np.maximum(1, np.round(tp.width * tv.px_per_mm).astype(int))
    for a, b, t in zip(p0, p1, th, strict=True):
        a, b = (int(a[0]), int(a[1])), (int(b[0]), int(b[1]))
        cv2.line(img, a, b, 200, int(t), cv2.LINE_AA, shift=4)
        cv2.circle(img, a, int(t) * 8, 200, -1, cv2.LINE_AA, shift=4)
        cv2.circle(img, b, int(t) * 8, 200, -1, cv2.LINE_AA, shift=4)
    return img


def _stack(n_layers: int, n_segments: int) -> Toolpath:
    base = dense_layer(n_segments)
    S, E, Z = [], [], []
    for i in range(n_layers):
        s, e = base.start.copy(), base.end.copy()
        if i % 2:  # mirror: -45 deg infill on odd layers
            s[:, 0] *= -1
            e[:, 0] *= -1
        S.append(s)
        E.append(e)
        Z.append(np.full(len(s), 0.3 * (i + 1)))
    return Toolpath.from_segments(np.concatenate(S), np.concatenate(E), np.concatenate(Z), 0.45, layer_height=0.3)


def run(n_segments: int = 20_000, repeats: int = 7) -> dict:
    tp = dense_layer(n_segments)
    settings = RenderSettings()
    sr = StackRenderer(tp, TV, settings)
    sr.render(0)  # JIT warm-up
    times = []
    for _ in range(repeats):
        sr.reset()
        t = time.perf_counter()
        out = sr.render(0)
        times.append(time.perf_counter() - t)
    fast_ms = statistics.median(times) * 1000
    cv2.imwrite(os.environ.get("LAYERWATCH_BENCH_PNG", "/tmp/bench_render_fast.png"), out.image)

    stack = _stack(6, n_segments)
    t = time.perf_counter()
    n = sum(1 for _ in render_stack(stack, TV, settings))
    stack_ms = (time.perf_counter() - t) / n * 1000

    # camera-view reference (the pipeline's default): the same layer seen from a camera at 45 deg
    # in front of the printer, 300 mm away, through the top of the 6-layer stack
    cam = np.array([0.0, -212.0, 212.0])
    sr6 = StackRenderer(stack, TV, settings)
    sr6.render(stack.n_layers - 1, cam)  # JIT warm-up
    view = []
    for _ in range(repeats):
        t = time.perf_counter()
        sr6.render(stack.n_layers - 1, cam)  # layers already rasterised: shading + ray march
        view.append(time.perf_counter() - t)
    top = []
    for _ in range(repeats):
        t = time.perf_counter()
        sr6.render(stack.n_layers - 1)
        top.append(time.perf_counter() - t)
    view_ms, top_ms = statistics.median(view) * 1000, statistics.median(top) * 1000

    t = time.perf_counter()
    naive_cv2(tp, TV)
    naive_ms = (time.perf_counter() - t) * 1000

    res = {"segments": tp.n_segments, "fast_ms": fast_ms, "stack_ms_per_layer": stack_ms,
           "naive_cv2_ms": naive_ms, "blender_ms": None, "camera_view_extra_ms": view_ms - top_ms}
    print(f"layer: {tp.n_segments} segments, {TV.shape[1]}x{TV.shape[0]} px, 0.45 mm beads, one core")
    print(f"fast render_layer (from scratch): {fast_ms:.1f} ms/layer (target <= 50 ms)")
    print(f"fast render_stack (incremental, {n} layers of {n_segments}): {stack_ms:.1f} ms/layer")
    print(f"baseline naive cv2.line/circle per segment (no shading): {naive_ms:.1f} ms "
          f"-> ratio {naive_ms / fast_ms:.1f}x")
    print(f"camera-view reference (shade + ray march, layer already rasterised): {view_ms:.1f} ms vs "
          f"top view {top_ms:.1f} ms -> +{view_ms - top_ms:.1f} ms per layer")

    if shutil.which("blender") and os.environ.get("LAYERWATCH_BENCH_BLENDER", "1") != "0":
        from layerwatch.render.blender import render_layer_blender

        samples = int(os.environ.get("LAYERWATCH_BENCH_SAMPLES", "16"))
        bs = settings.model_copy(update={"blender_samples": samples})
        t = time.perf_counter()
        render_layer_blender(tp, 0, TV, bs, threads=1)
        blender_ms = (time.perf_counter() - t) * 1000
        res["blender_ms"] = blender_ms
        print(f"baseline Blender Cycles ({samples} samples, 1 thread, incl. start-up): {blender_ms / 1000:.1f} s "
              f"-> ratio {blender_ms / fast_ms:.0f}x (target >= 1000x)")
    else:
        print("Blender not run (no `blender` on PATH or LAYERWATCH_BENCH_BLENDER=0)")
    return res


def test_bench_render():
    res = run()
    assert res["fast_ms"] > 0


if __name__ == "__main__":
    run()
