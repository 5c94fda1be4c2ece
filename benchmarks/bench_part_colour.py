"""What the off-colour tests of the printed layer and its rim add to the 1080p layer, timed in isolation.

Run: ``python benchmarks/bench_part_colour.py [--rounds 20]``.

The per-layer budget (``bench_layer_1080p.py``: 60 ms on one core) cannot
resolve a millisecond on a shared machine, so this times only
:func:`~layerwatch.analysis.part_colour.off_colour_blocks` on the inputs the
step gives it: the recommended pipeline runs the bundled example part's
layers 2-19, photographed at 1920 x 1080 with a blue hex key lying on the
part from layer 8, and the arguments of each call are kept; then each call
is repeated ``--rounds`` times, timed by the process's CPU time on one thread
(``cv2.setNumThreads(1)``). Printed: the median per layer and the largest
layer's median, ms; the same for :func:`~layerwatch.analysis.part_colour.rim_material`
on the same arguments (the step calls it on analysed layers when the scene
channel is on).
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

import layerwatch.analysis.part_colour as part_colour
import layerwatch.pipeline.step as lw_step
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.pipeline.config import recommended_config
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera

LAYERS = range(2, 20)


def _calls() -> list[tuple]:
    """The arguments of the step's off-colour calls on layers :data:`LAYERS` of the example part at 1080p."""
    tp = read_toolpath(PART_GCODE)
    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    cam = default_camera(tv, image_size=(1920, 1080))
    pipe = LayerPipeline(tp, cam, cfg, memo=2)
    key = Failure(type="foreign_body", onset=8, size_mm=10.0, center_mm=(100.0, 100.0), seed=7)
    sim = PrintSimulator(tp, cam, pipe.topview, (key,), seed=4)
    pipe.new_print(sim.bed_photo())
    calls: list[tuple] = []
    real = part_colour.off_colour_blocks

    def keep(*args):
        calls.append(args)
        return real(*args)

    lw_step.off_colour_blocks = keep  # type: ignore[assignment]
    try:
        for i in LAYERS:
            pipe.process(sim.frame(i).photo, i)
    finally:
        lw_step.off_colour_blocks = real  # type: ignore[assignment]
    return calls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=20)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    calls = _calls()
    medians = []
    for c in calls:
        t = []
        for _ in range(args.rounds):
            t0 = time.process_time()
            part_colour.off_colour_blocks(*c)
            t.append((time.process_time() - t0) * 1e3)
        medians.append(float(np.median(t)))
    found = sum(int(np.any(part_colour.off_colour_blocks(*c))) for c in calls)
    print(f"off_colour_blocks on {len(calls)} layers at 1920x1080 (top view {calls[0][0].shape[1]}x"
          f"{calls[0][0].shape[0]} px), {args.rounds} rounds, CPU time, one thread:")
    print(f"  median per layer {np.median(medians):.3f} ms, largest {max(medians):.3f} ms; "
          f"layers with off-colour blocks: {found}")
    rim = []
    for top_bgr, fp, valid, cell_px, _, px_per_mm in calls:
        t = []
        for _ in range(args.rounds):
            t0 = time.process_time()
            part_colour.rim_material(top_bgr, fp, valid, cell_px, px_per_mm)
            t.append((time.process_time() - t0) * 1e3)
        rim.append(float(np.median(t)))
    print(f"rim_material on the same layers: median per layer {np.median(rim):.3f} ms, largest {max(rim):.3f} ms")


if __name__ == "__main__":
    main()
