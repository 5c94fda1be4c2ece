"""CPU per warm farm frame, step by step (the per-step tables of docs/farm.md).

Run: ``python benchmarks/farm_steps.py [--printers 3] [--first 8]`` in a checkout (``PYTHONPATH`` at its ``src``).
Each printer of :mod:`farm_capacity` (its own shifted, gained 1080p JPEG snapshots of the example part) runs
its job's layers through a :class:`~layerwatch.farm.monitor.FarmMonitor` as the capacity benchmark runs it,
with the pool's work in the calling thread so that one clock sees it all; the layers before ``--first`` warm
the printer up (scene baseline, reference stack) and are not counted; the printers are interleaved layer by
layer, as a farm's frames are. Each step is the CPU time (``time.process_time``) spent inside the function
that does it, inclusive, a step inside another one counted in both (the reference's render inside the scene
channel's first call, the lag check's warp inside the lag check); ``total`` is the whole frame. No profiler:
the figures are the code's own; ``--same-file``: the printers share their references, the first printer of a
layer renders it (the machine's load still shows in them: run two checkouts one after the
other, twice, and compare the pairs).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _steps() -> list[tuple[str, object, str]]:
    """(step name, owner, attribute) of each timed function."""
    from layerwatch.analysis.failure_typing import FailureTyper
    from layerwatch.farm import remote
    from layerwatch.monitor import cameras, frame_checks
    from layerwatch.pipeline import step
    from layerwatch.pipeline.checks import JobChecks
    from layerwatch.pipeline.layer_change import LayerChange
    from layerwatch.pipeline.scene import SceneModel
    from layerwatch.render import volume

    return [
        ("JPEG decode", cameras, "decode_image"),
        ("stale-frame fingerprint", cameras.StaleCheck, "__call__"),
        ("stale-frame fingerprint (file)", cameras.StaleCheck, "file"),
        ("camera-fault gate", frame_checks.FrameChecks, "gate"),
        ("of it the bed markers", frame_checks.FrameChecks, "marker_positions"),
        ("reference: render + HOG", step.LayerPipeline, "reference"),
        ("of it the volume ray march", volume, "view_through_volume"),
        ("scene channel: observe", SceneModel, "observe"),
        ("scene channel: result + update", step.LayerPipeline, "_scene_result"),
        ("warp to the top view", step.LayerPipeline, "_top_views"),
        ("view shift", step, "measure_view_shift"),
        ("HOG analysis", step, "analyze_layer"),
        ("failure typing", FailureTyper, "type_result"),
        ("job checks", JobChecks, "after_layer"),
        ("layer change", LayerChange, "judge"),
        ("thumbnail", remote, "_thumbnail"),
        ("lag check", frame_checks.FrameChecks, "late"),
    ]


def timed(printers: int, first: int, same_file: bool = False) -> tuple[dict[str, float], int]:
    """CPU ms per counted frame of each step, and the frames counted."""
    import farm_capacity as fc  # noqa: PLC0415 - sets the thread limits before NumPy/OpenCV load

    spent: dict[str, float] = defaultdict(float)
    counting = [False]
    depth: dict[str, int] = defaultdict(int)

    def wrap(name: str, fn):
        def inner(*a, **k):
            if not counting[0] or depth[name]:
                return fn(*a, **k)
            depth[name] += 1
            t = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                spent[name] += time.process_time() - t
                depth[name] -= 1
        return inner

    for name, owner, attr in _steps():
        if hasattr(owner, attr):
            setattr(owner, attr, wrap(name, getattr(owner, attr)))
    # a module that imported the march by name calls its own binding
    from layerwatch.render import fast
    from layerwatch.render import volume as volume_mod
    if hasattr(fast, "view_through_volume"):
        fast.view_through_volume = volume_mod.view_through_volume

    scene = fc.Scene(layers=33)
    n = scene.toolpath.n_layers
    jpegs = {(k, i): scene.jpeg(k, i) for k in range(printers) for i in range(n)}
    runs = []
    for k in range(printers):
        runner, p, pool = fc.inline_printer(scene, k, same_file)
        for i in range(first):
            runner.frame(p, i, jpegs[k, i])
        runs.append((runner, p, pool))
    frames = 0
    counting[0] = True
    for i in range(first, n):
        for runner, p, _ in runs:
            t = time.process_time()
            runner.frame(p, i, jpegs[p.index, i])
            spent["total"] += time.process_time() - t
            frames += 1
    counting[0] = False
    for runner, p, pool in runs:
        runner.close([p])
        pool.close()
    return {k: v / frames * 1e3 for k, v in spent.items()}, frames


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--printers", type=int, default=3)
    ap.add_argument("--first", type=int, default=8, help="first counted layer (the ones before warm up)")
    ap.add_argument("--same-file", action="store_true",
                    help="the printers print one file with one camera model and share its references")
    a = ap.parse_args(argv)
    if a.printers < 1 or not 1 <= a.first < 33:
        ap.error("--printers >= 1, --first in 1..32")
    ms, frames = timed(a.printers, a.first, a.same_file)
    print(f"CPU ms per warm frame, {frames} frames ({a.printers} printers{' sharing one file' if a.same_file else ''} "
          f"x layers {a.first}-32), "
          f"load average {os.getloadavg()[0]:.1f}")
    for name, _, _ in _steps():
        if name in ms:
            print(f"  {name:34s} {ms[name]:6.1f}")
    print(f"  {'total':34s} {ms['total']:6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
