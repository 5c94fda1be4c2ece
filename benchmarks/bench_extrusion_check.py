"""Per-layer cost of the nothing-extruded check at 1080p, against the check of an earlier revision (issue 21).

Both :class:`~layerwatch.pipeline.checks.JobChecks` (the current one and the one of ``--rev``, imported
from git in this process by :mod:`baseline_revision`) judge the same simulated 1080p photos of the
example part, layer by layer, interleaved; the script prints the median CPU ms per layer of each, the
ratio, and how many layers got a different surface similarity where both judged the layer on its own
(the current check pools thin layers with the layer before, so those may differ by design).
One thread, as a farm worker runs. Say the machine's load (``uptime``) with the figures.

Run: ``python benchmarks/bench_extrusion_check.py [--rev 74c3e36 --rounds 5]``
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from baseline_revision import load_revision  # noqa: E402

import layerwatch.pipeline.checks as lw_checks  # noqa: E402
from layerwatch.analysis.result import LayerResult  # noqa: E402
from layerwatch.evaluate.checks import _pipeline_footprints, _setup, job_checks  # noqa: E402
from layerwatch.examples import PART_GCODE  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.geometry.warp import TopViewWarper  # noqa: E402
from layerwatch.simulate import PrintSimulator  # noqa: E402

LAYERS = range(0, 24)


def run(rev: str = "74c3e36", rounds: int = 5, size: tuple[int, int] = (1920, 1080)) -> dict:
    """Median CPU ms per layer of the current check and of the check at ``rev``, and where they disagree."""
    cv2.setNumThreads(1)
    tp = read_toolpath(PART_GCODE.read_bytes())
    tv, cam = _setup(tp, size)
    footprint = _pipeline_footprints(tp, cam, tv)  # what the pipeline hands the check
    sim = PrintSimulator(tp, cam, tv, seed=7)
    photos = {i: sim.frame(i).photo for i in LAYERS}
    ours = job_checks(tp, cam, tv)
    checks = {"ours": ours}
    old = load_revision(rev, ["layerwatch.pipeline.checks"])
    if old is not None:
        mod = old["layerwatch.pipeline.checks"]
        assert mod.__file__ != lw_checks.__file__, "the baseline is the current code"
        checks["old"] = mod.JobChecks(cam, tv, TopViewWarper(cam, tv), ours.config, None,
                                      reach_mm=mod.print_reach_mm(tp), top_z_mm=mod.print_top_z_mm(tp))
    cpu: dict[str, list[float]] = {k: [] for k in checks}
    sims: dict[str, dict[int, float]] = {k: {} for k in checks}
    pooled: set[int] = set()
    for r in range(rounds + 1):  # the first round builds the plane maps: not timed
        for c in checks.values():
            c.new_print()
        for i, photo in photos.items():
            for name, c in checks.items():
                t = time.process_time()
                c.after_layer(LayerResult(layer=i, z=float(tp.layers[i].z)), photo, i, footprint)
                if r:
                    cpu[name].append((time.process_time() - t) * 1e3)
                sims[name][i] = c.similarity[0]
            if ours.pooled:
                pooled.add(i)
    differ = []
    if "old" in checks:
        for i in sorted(set(LAYERS) - pooled):
            a, b = sims["ours"][i], sims["old"][i]
            if np.isfinite(a) and np.isfinite(b) and abs(a - b) > 1e-3:
                differ.append(i)
    return {"ms": {k: float(np.median(v)) for k, v in cpu.items()}, "rev": rev if old is not None else None,
            "differ": differ, "layers": len(photos), "rounds": rounds, "pooled": sorted(pooled), "load": os.getloadavg()[0],
            "sims": sims}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", default="74c3e36", help="git revision of the baseline check")
    ap.add_argument("--rounds", type=int, default=5, help="timed passes over the layers")
    a = ap.parse_args(argv)
    r = run(a.rev, a.rounds)
    ms = r["ms"]
    print(f"nothing-extruded check, 1920x1080 photos, {r['layers']} layers x {r['rounds']} rounds, one thread, "
          f"load {r['load']:.2f}: ours {ms['ours']:.2f} ms/layer (median CPU)")
    if r["rev"] is None:
        print(f"  baseline {a.rev} not available (no git history): no ratio")
    else:
        print(f"  check at {r['rev']}: {ms['old']:.2f} ms/layer -> ratio {ms['old'] / ms['ours']:.2f}x faster; "
              f"layers judged alone by ours and by both with a different similarity (> 1e-3): {r['differ'] or 'none'} "
              f"(pooled by ours: {r['pooled'] or 'none'})")
    return r


if __name__ == "__main__":
    main()
