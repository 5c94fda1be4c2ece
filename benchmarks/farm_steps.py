"""CPU per warm farm frame, step by step (the per-step tables of docs/farm.md).

Run: ``python benchmarks/farm_steps.py [--printers 3] [--first 8] [--jobs 1]`` in a checkout (``PYTHONPATH`` at its ``src``).
Each printer of :mod:`farm_capacity` (its own shifted, gained 1080p JPEG snapshots of the example part) runs
its job's layers through a :class:`~layerwatch.farm.monitor.FarmMonitor` as the capacity benchmark runs it,
with the pool's work in the calling thread so that one clock sees it all; the layers before ``--first`` warm
the printer up (scene baseline, reference stack) and are not counted; the printers are interleaved layer by
layer, as a farm's frames are. ``--jobs J``: each printer then prints the part ``J - 1`` times more, a new job
(monitor and pipeline built at its layer 0, as the capacity benchmark's printers start a job) each time; the
first frames of those jobs get columns of their own (``job start``: layer 0 with the job's set-up; layers 1-3)
beside the warm frames, with the set-up's own steps (``_job_steps``). Each step is the CPU time (``time.process_time``) spent inside the function
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


def _job_steps() -> list[tuple[str, object, str]]:
    """(step name, owner, attribute) of what a job's start runs once (timed with ``--jobs``)."""
    import farm_capacity as fc  # noqa: PLC0415

    from layerwatch.geometry import markers
    from layerwatch.pipeline.checks import JobChecks
    from layerwatch.pipeline.scene import SceneModel

    return [
        ("job set-up (monitor + pipeline)", fc.Runner, "attach"),
        ("of it the scene model's view maps", SceneModel, "__init__"),
        ("checks' box maps", JobChecks, "_box_maps"),
        ("bed markers found", markers, "detect_dots"),
    ]


#: the columns of ``--jobs``: the warm frames, a job's first frame (with its set-up) and its next three
PHASES = ("warm", "job start", "layers 1-3")


def timed(printers: int, first: int, same_file: bool = False,
          jobs: int = 1) -> tuple[dict[str, dict[str, float]], dict[str, int]]:
    """CPU ms per counted frame of each step, by phase (:data:`PHASES`), and the frames counted in each."""
    import farm_capacity as fc  # noqa: PLC0415 - sets the thread limits before NumPy/OpenCV load

    spent: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    phase: list[str | None] = [None]  # the phase being counted (None: not counting)
    depth: dict[str, int] = defaultdict(int)

    def wrap(name: str, fn):
        def inner(*a, **k):
            now = phase[0]
            if now is None or depth[name]:
                return fn(*a, **k)
            depth[name] += 1
            t = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                spent[now][name] += time.process_time() - t
                depth[name] -= 1
        return inner

    for name, owner, attr in _steps() + (_job_steps() if jobs > 1 else []):
        if hasattr(owner, attr):
            setattr(owner, attr, wrap(name, getattr(owner, attr)))
    # a module that imported the march by name calls its own binding
    from layerwatch.render import fast
    from layerwatch.render import volume as volume_mod
    if hasattr(fast, "view_through_volume"):
        fast.view_through_volume = volume_mod.view_through_volume
    from layerwatch.geometry import markers
    from layerwatch.monitor import marker_watch
    if hasattr(marker_watch, "detect_dots"):
        marker_watch.detect_dots = markers.detect_dots

    scene = fc.Scene(layers=33)
    n = scene.toolpath.n_layers
    jpegs = {(k, i): scene.jpeg(k, i) for k in range(printers) for i in range(n)}
    runs = []
    for k in range(printers):
        runner, p, pool = fc.inline_printer(scene, k, same_file)
        for i in range(first):
            runner.frame(p, i, jpegs[k, i])
        runs.append((runner, p, pool))
    frames: dict[str, int] = defaultdict(int)
    for job in range(jobs):
        for i in range(first if job == 0 else 0, n):  # a job after the first starts at its layer 0 (a new job)
            phase[0] = "warm" if i >= first else "job start" if i == 0 else "layers 1-3" if i < 4 else None
            for runner, p, _ in runs:
                t = time.process_time()
                runner.frame(p, i, jpegs[p.index, i])
                if phase[0] is not None:
                    spent[phase[0]]["total"] += time.process_time() - t
                    frames[phase[0]] += 1
            phase[0] = None
    for runner, p, pool in runs:
        runner.close([p])
        pool.close()
    return {ph: {k: v / frames[ph] * 1e3 for k, v in spent[ph].items()} for ph in frames}, dict(frames)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--printers", type=int, default=3)
    ap.add_argument("--first", type=int, default=8, help="first counted layer (the ones before warm up)")
    ap.add_argument("--same-file", action="store_true",
                    help="the printers print one file with one camera model and share its references")
    ap.add_argument("--jobs", type=int, default=1,
                    help="jobs each printer prints; the first frames of jobs 2.. get their own columns (default 1)")
    a = ap.parse_args(argv)
    if a.printers < 1 or not 1 <= a.first < 33 or a.jobs < 1:
        ap.error("--printers >= 1, --first in 1..32, --jobs >= 1")
    ms, frames = timed(a.printers, a.first, a.same_file, a.jobs)
    print(f"CPU ms per warm frame, {frames['warm']} frames ({a.printers} printers{' sharing one file' if a.same_file else ''} "
          f"x layers {a.first}-32)"
          + (f"; per job start (layer 0, its set-up included) and per frame of layers 1-3, jobs 2-{a.jobs}: "
             f"{frames['job start']} and {frames['layers 1-3']} frames" if a.jobs > 1 else "")
          + f", load average {os.getloadavg()[0]:.1f}")
    phases = [ph for ph in PHASES if ph in ms]
    if len(phases) > 1:
        print(f"  {'':34s} " + " ".join(f"{ph:>10s}" for ph in phases))
    for name, _, _ in _steps() + (_job_steps() if a.jobs > 1 else []) + [("total", None, "")]:
        if any(name in ms[ph] for ph in phases):
            print(f"  {name:34s} " + " ".join(f"{ms[ph].get(name, 0.0):10.1f}" for ph in phases))
    return 0


if __name__ == "__main__":
    sys.exit(main())
