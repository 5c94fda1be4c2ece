"""Issue 18 study: does the camera's own resolution as the top-view scale help infill and thin-wall defects?

Run: ``python tools/study_resolution.py [-n 240] [--width 1920] [--seed 0]``.

The same simulated sample (``layerwatch evaluate``'s harness, the bundled
example part, the recommended settings: jaccard at T_S 0.20 plus the scene
channel) is scored with the top view at

* ``fixed``: the paper's 6.67 px/mm;
* ``camera``: the camera's median resolution over the observed square
  (:func:`~layerwatch.geometry.resolution.camera_px_per_mm`), HOG cells of 8 px
  (finer cells in mm);
* ``camera, cells in mm``: the camera's scale with the cell side scaled so that
  a cell covers the same millimetres as 8 px at 6.67 px/mm (only the sampling
  changes);
* ``fixed, finer cells``: 6.67 px/mm with the cells of the camera variant in
  mm (8 px at the camera's scale: only the cell size changes).

Prints, per variant, the AUROC of the recommended setting's a% for each
failure type against the clean layers, the mean a% of clean layers, and the
per-layer time of the step; a Markdown table for ``docs/evaluation/resolution.md``.
"""

from __future__ import annotations

import argparse
import os
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from layerwatch.analysis.settings import METRIC_NAMES  # noqa: E402
from layerwatch.evaluate.harness import THRESHOLDS, run_evaluation  # noqa: E402
from layerwatch.evaluate.stats import roc_auc  # noqa: E402
from layerwatch.examples import PART_CONFIG, PART_GCODE  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.geometry.resolution import camera_px_per_mm  # noqa: E402
from layerwatch.pipeline.config import JobConfig, recommended_config  # noqa: E402
from layerwatch.simulate import FAILURE_TYPES, default_camera  # noqa: E402


def setting_scores(data, config: JobConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(kinds, a%)`` per record at the config's own measure and threshold."""
    m = METRIC_NAMES.index(config.analysis.metric)
    j = int(np.argmin(np.abs(THRESHOLDS - config.analysis.threshold)))
    kinds = np.array([r.kind for r in data.records])
    return kinds, np.array([r.a[m, j] for r in data.records])


def auroc_table(data, config: JobConfig) -> dict[str, float]:
    """AUROC of the setting's a% per failure type (failed layers vs all clean layers)."""
    kinds, a = setting_scores(data, config)
    clean = a[kinds == "clean"]
    out = {t: roc_auc(a[kinds == t], clean) for t in FAILURE_TYPES if (kinds == t).any()}
    out["clean mean a%"] = float(100 * clean.mean()) if clean.size else float("nan")
    return out


def variants(base: JobConfig, camera) -> dict[str, JobConfig]:
    tv = base.topview
    cam_scale = camera_px_per_mm(camera, tv.center_mm, tv.width_mm, tv.height_mm)
    cell_mm = base.analysis.cell_px / tv.px_per_mm
    cells = max(2, int(round(cell_mm * cam_scale)))
    fine = max(2, int(round(base.analysis.cell_px * tv.px_per_mm / cam_scale)))  # the camera scale's cells in mm
    return {
        f"fixed {tv.px_per_mm:.2f} px/mm": base,
        f"camera {cam_scale:.2f} px/mm, 8-px cells": base.model_copy(
            update={"topview": tv.model_copy(update={"px_per_mm": cam_scale})}),
        f"camera {cam_scale:.2f} px/mm, {cells}-px cells": base.model_copy(
            update={"topview": tv.model_copy(update={"px_per_mm": cam_scale}),
                    "analysis": base.analysis.model_copy(update={"cell_px": cells})}),
        f"fixed {tv.px_per_mm:.2f} px/mm, {fine}-px cells": base.model_copy(
            update={"analysis": base.analysis.model_copy(update={"cell_px": fine})}),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", "--layers", type=int, default=240)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variants", type=int, nargs="*", default=[0, 1, 2, 3], help="which variants (0-3)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    tp = read_toolpath(PART_GCODE)
    base = recommended_config(PART_CONFIG)
    camera = default_camera(base.topview.topview(), image_size=(args.width, int(round(args.width * 9 / 16))))
    rows = {}
    for name, cfg in [v for k, v in enumerate(variants(base, camera).items()) if k in args.variants]:
        t = time.perf_counter()
        data = run_evaluation(tp, cfg, camera, n_layers=args.layers, seed=args.seed)
        rows[name] = auroc_table(data, cfg)
        rows[name]["s/frame"] = (time.perf_counter() - t) / max(1, len(data.records))
        print(name, {k: round(v, 3) for k, v in rows[name].items()}, f"errors: {len(data.errors)}", flush=True)
    cols = [c for c in (*FAILURE_TYPES, "clean mean a%", "s/frame") if any(c in r for r in rows.values())]
    print(f"\n{len(data.records)} layers, {args.width} px wide photos, seed {args.seed}\n")
    print("| top view | " + " | ".join(cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for name, r in rows.items():
        print(f"| {name} | " + " | ".join(f"{r.get(c, float('nan')):.3f}" for c in cols) + " |")


if __name__ == "__main__":
    main()
