"""Picture of a failure's truth against what the monitor marks, on one simulated photo of the example part.

Run: ``PYTHONPATH=<src> python tools/truth_picture.py [--gcode FILE] [--kind detachment] [--onset 12]
[--layer 16] [--size 4] [--seed 3] [--out docs/evaluation/parts/truth_detachment.jpg]``

The bundled example part (or ``--gcode``, its settings as ``layerwatch evaluate --gcode`` derives
them) with the recommended settings and a 1280 x 720 camera; one print with the failure, fed to the pipeline in
series mode up to ``--layer``. Left: the photo's top view. Right: the same with
the truth (``SimFrame.truth_area``, :mod:`layerwatch.simulate.truth`) in green,
what the result marks (:func:`~layerwatch.evaluate.modes.marked_area`) in
magenta, both in white; the IoU and the typed kind in the title bar.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from layerwatch.evaluate.modes import marked_area, mode_score
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.pipeline.config import observed_square, resolve_config
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gcode", type=Path, default=None)
    ap.add_argument("--kind", default="detachment")
    ap.add_argument("--onset", type=int, default=12)
    ap.add_argument("--layer", type=int, default=16)
    ap.add_argument("--size", type=float, default=4.0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("docs/evaluation/parts/truth_detachment.jpg"))
    a = ap.parse_args()
    tp = read_toolpath(a.gcode or PART_GCODE)
    cfg = (resolve_config(PART_CONFIG, recommended=True) if a.gcode is None
           else resolve_config(None, recommended=True, gcode=observed_square(tp.bounds))).config
    cam = default_camera(cfg.topview.topview(), image_size=(1280, 720))
    cfg = cfg.for_camera(cam)
    tv = cfg.topview.topview()
    sim = PrintSimulator(tp, cam, tv, [Failure(a.kind, onset=a.onset, size_mm=a.size, seed=a.seed)], seed=a.seed)
    pipe = LayerPipeline(tp, cam, cfg, memo=tp.n_layers)
    pipe.new_print(sim.bed_photo() if pipe.scene is not None else None)
    for i in range(a.layer + 1):
        frame = sim.frame(i)
        res = pipe.process(frame.photo, i)
    assert pipe.last_top is not None and frame.truth_area is not None
    top = pipe.last_top if pipe.last_top.ndim == 3 else cv2.cvtColor(pipe.last_top, cv2.COLOR_GRAY2BGR)
    marked = marked_area(res, tv)
    truth = frame.truth_area
    m = mode_score(res, truth, tv, sim.failures[0].offset)
    over = top.copy()
    over[truth & ~marked] = (0.4 * over[truth & ~marked] + (0, 150, 0)).astype(np.uint8)
    over[marked & ~truth] = (0.4 * over[marked & ~truth] + (150, 0, 150)).astype(np.uint8)
    over[marked & truth] = (0.4 * over[marked & truth] + (150, 150, 150)).astype(np.uint8)
    ys, xs = np.nonzero(truth | marked | (top.max(-1) > 0))
    pad = 20
    crop = (slice(max(ys.min() - pad, 0), ys.max() + pad), slice(max(xs.min() - pad, 0), xs.max() + pad))
    pic = np.hstack([top[crop], over[crop]])
    bar = np.zeros((40, pic.shape[1], 3), np.uint8)
    text = (f"{a.kind} {a.size:g} mm, onset {a.onset}, layer {a.layer}: IoU {m.iou:.2f}, typed {m.kind}   "
            "green truth / magenta marked / white both")
    cv2.putText(bar, text, (8, 27), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(a.out), np.vstack([bar, pic]), [cv2.IMWRITE_JPEG_QUALITY, 88])
    print(text)


if __name__ == "__main__":
    main()
