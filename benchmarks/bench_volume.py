"""Speed of the occupancy-volume reference against today's height-map reference (issue 18: <= 50 ms).

Run: ``python benchmarks/bench_volume.py`` or ``pytest benchmarks/bench_volume.py -s``.
One core (``NUMBA_NUM_THREADS=1``; the kernels have no ``prange``), 600 x 600 px
(90 mm at 6.67 px/mm), camera at 45 deg in front of the printer, 300 mm away:
the pipeline's default camera-view reference (``render.view = "camera"``).
Wall-clock time; ``LAYERWATCH_BENCH_CLOCK=cpu`` times the thread's CPU time
instead (on a shared, busy machine wall-clock time includes waiting for a core).

Timed in the same process, ``render.reference = "height"`` (baseline: today's
renderer) and ``"volume"``, the two run in turn in every round so that both
see the same machine load:

* one layer of 20,000 segments from scratch (rasterise + shade + camera ray
  march; for the volume also the layer's footprint packed into the stack),
  median of several runs -- the issue's budget;
* the same layer on top of 5 others (6-layer stack), the march only;
* a tall part (``window_part``: bridge, windows, overhang; 70 layers) rendered
  layer by layer, mean per layer, and the memory of its occupancy stack.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from layerwatch.geometry.topview import TopView  # noqa: E402
from layerwatch.render.fast import StackRenderer  # noqa: E402
from layerwatch.render.settings import RenderSettings  # noqa: E402
from layerwatch.simulate import default_camera  # noqa: E402
from layerwatch.simulate.parts import window_part  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "render"))  # test-only part generators
from bench_render import _stack  # noqa: E402
from render_parts import dense_layer  # noqa: E402

cv2.setNumThreads(1)
TV = TopView(6.67, 90.0, 90.0, (0.0, 0.0))
CAM = np.array([0.0, -212.0, 212.0])
#: the variants timed: today's height map and volume (the march through each layer's plane) and the volume
#: marched once per camera pixel and kept (``render.march = "image"``)
REFS = ("height", "volume", "image")
CAMERA = default_camera(TV, distance_mm=float(np.hypot(*CAM[1:])))  # centre CAM: 45 deg, in front


def _renderer(tp, ref: str) -> StackRenderer:
    if ref == "image":
        return StackRenderer(tp, TV, RenderSettings(reference="volume", march="image"), CAMERA)
    return StackRenderer(tp, TV, RenderSettings(reference=ref))
#: LAYERWATCH_BENCH_CLOCK=cpu times the thread's CPU time (a busy shared machine inflates wall-clock time)
_clock = time.thread_time if os.environ.get("LAYERWATCH_BENCH_CLOCK") == "cpu" else time.perf_counter


def _interleaved_ms(fns: dict, repeats: int) -> dict:
    """Median ms of each callable, the callables run in turn each round (same machine load for all)."""
    times: dict = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t = _clock()
            fn()
            times[k].append(_clock() - t)
    return {k: statistics.median(v) * 1000 for k, v in times.items()}


def from_scratch(n_segments: int, repeats: int) -> dict:
    """One layer of ``n_segments`` rendered from an empty stack, camera view, ms per reference."""
    tp = dense_layer(n_segments)
    fns = {}
    for ref in REFS:
        sr = _renderer(tp, ref)
        sr.render(0, CAM)  # JIT warm-up

        def once(sr=sr):
            sr.reset()
            sr.render(0, CAM)

        fns[ref] = once
    return _interleaved_ms(fns, repeats)


def march_on_stack(n_segments: int, repeats: int) -> dict:
    """The top of a 6-layer stack already rasterised: shading + ray march, ms per reference."""
    stack = _stack(6, n_segments)
    fns = {}
    for ref in REFS:
        sr = _renderer(stack, ref)
        sr.render(stack.n_layers - 1, CAM)
        fns[ref] = lambda sr=sr: sr.render(stack.n_layers - 1, CAM)
    return _interleaved_ms(fns, repeats)


def tall_part() -> tuple[dict, int]:
    """``window_part`` layer by layer (both references in turn): mean ms per layer, occupancy bytes at the end."""
    tp = window_part()
    srs = {ref: _renderer(tp, ref) for ref in REFS}
    total = dict.fromkeys(REFS, 0.0)
    for i in range(tp.n_layers):
        for ref, sr in srs.items():
            t = _clock()
            sr.render(i, CAM)
            total[ref] += _clock() - t
    rays = srs["image"].rays
    return ({ref: v / tp.n_layers * 1000 for ref, v in total.items()}, srs["volume"].volume.nbytes,
            0 if rays is None else rays.nbytes)


def run(n_segments: int = 20_000, repeats: int = 7) -> dict:
    scratch, march = from_scratch(n_segments, repeats), march_on_stack(n_segments, repeats)
    res = {ref: {"scratch_ms": scratch[ref], "march_ms": march[ref]} for ref in REFS}
    tall, nbytes, ray_bytes = tall_part()
    for ref in REFS:
        res[ref]["tall_ms"] = tall[ref]
    res["volume"]["bytes"] = nbytes
    h, v, im = res["height"], res["volume"], res["image"]
    print(f"{n_segments} segments, {TV.shape[1]}x{TV.shape[0]} px, camera view, one core; "
          f"{'wall-clock' if _clock is time.perf_counter else 'CPU (thread) time'}")
    print(f"from scratch: height map {h['scratch_ms']:.1f} ms, volume {v['scratch_ms']:.1f} ms "
          f"-> ratio {v['scratch_ms'] / h['scratch_ms']:.2f}x (target <= 50 ms)")
    print(f"top of a 6-layer stack (march): height map {h['march_ms']:.1f} ms, volume {v['march_ms']:.1f} ms "
          f"-> ratio {v['march_ms'] / h['march_ms']:.2f}x")
    print(f"window_part, 70 layers one by one: height map {h['tall_ms']:.1f} ms/layer, volume "
          f"{v['tall_ms']:.1f} ms/layer -> ratio {v['tall_ms'] / h['tall_ms']:.2f}x; occupancy "
          f"{v['bytes'] / 1e6:.2f} MB (500 layers at this size: {500 * TV.shape[0] * ((TV.shape[1] + 7) // 8) / 1e6:.1f} MB)")
    print(f"march = 'image' (kept camera rays, {ray_bytes / 1e6:.2f} MB of hits on the window part): from scratch "
          f"{im['scratch_ms']:.1f} ms ({im['scratch_ms'] / v['scratch_ms']:.2f}x the plane march), top of the stack "
          f"{im['march_ms']:.1f} ms ({im['march_ms'] / v['march_ms']:.2f}x), window_part {im['tall_ms']:.1f} ms/layer "
          f"({im['tall_ms'] / v['tall_ms']:.2f}x)")
    return res


def test_bench_volume():
    res = run(repeats=3)
    assert res["volume"]["scratch_ms"] > 0


if __name__ == "__main__":
    run()
