"""Issue 18 study: localisation IoU of the four kinds with a target, on a small sample, one code version per run.

Run: ``PYTHONPATH=<src> python tools/study_localisation.py --seed 5 [--per-kind 6] [--layers 400] [--out scores.json]``
(``--per-kind 0``: every scenario of the four kinds).

The evaluation's own plan (:func:`~layerwatch.evaluate.harness.plan_frames`: the
bundled example part, recommended settings, 1280 x 720 photos, 30 % of the
foreign bodies and spaghetti beside the part, about 400 photos planned) is
restricted to the first ``--per-kind`` scenarios of each of foreign body,
detachment, layer shift and spaghetti; each goes through
:func:`~layerwatch.evaluate.harness._scenario_records` in series mode with the
scenario seed the evaluation gives it, so a photo here is the photo of a
``layerwatch evaluate --layers 400 --beside-share 0.3 --seed S`` run.

Printed: the mean IoU per kind (failures >= 5 mm; every shift and detachment),
as the report counts it, the typed kinds per kind (the confusion matrix's rows)
and the displacement error of the photos whose covering region reports one. ``--out`` writes per photo the scenario, layer, kind,
IoU, whole-view score and typed kind, so that two code versions run at the
same moment (one ``PYTHONPATH`` each, e.g. a ``git worktree`` of the base)
can be compared photo by photo: identical scores and kinds mean identical
AUROCs and confusion matrices.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import layerwatch.evaluate.harness as harness  # noqa: E402
from layerwatch.examples import PART_CONFIG, PART_GCODE  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.pipeline.config import resolve_config  # noqa: E402
from layerwatch.simulate import default_camera  # noqa: E402

KINDS = ("foreign_body", "detachment", "layer_shift", "spaghetti")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--per-kind", type=int, default=6)
    ap.add_argument("--layers", type=int, default=400, help="the evaluation's --layers (its plan)")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG, recommended=True).config
    cam = default_camera(cfg.topview.topview(), image_size=(1280, 720))
    cfg = cfg.for_camera(cam)
    plan = harness.plan_frames(tp, a.layers, seed=a.seed, beside_share=0.3)
    taken = {k: 0 for k in KINDS}
    rows = []
    for k, (scen, layers) in enumerate(plan):
        kind = scen.failures[0].type if scen.failures else ""
        if kind not in taken or (a.per_kind > 0 and taken[kind] >= a.per_kind):
            continue
        taken[kind] += 1
        records, _ = harness._scenario_records(tp, cam, cfg, scen, layers, a.seed * 1000 + k, False, ("series",),
                                               None, lambda: None)
        for r in records:
            m = r.modes["series"]
            rows.append({"scenario": r.scenario, "layer": r.layer, "kind": r.kind, "size_mm": r.size_mm,
                         "iou": m.iou, "score": m.score, "typed": m.kind,
                         "displacement_error_mm": m.displacement_error_mm})
    ious: dict[str, list[float]] = {}
    for r in rows:
        if r["iou"] is not None and r["kind"] in KINDS and (r["size_mm"] >= 5 or r["kind"] in ("detachment", "layer_shift")):
            ious.setdefault(r["kind"], []).append(r["iou"])
    for kind in KINDS:
        v = ious.get(kind, [])
        typed: dict[str, int] = {}
        for r in rows:
            if r["kind"] == kind:
                typed[r["typed"]] = typed.get(r["typed"], 0) + 1
        errs = [r["displacement_error_mm"] for r in rows if r["kind"] == kind and r["displacement_error_mm"] is not None]
        disp = (f"  displacement within 0.5 mm {sum(e <= 0.5 for e in errs)}/{len(errs)} (median {np.median(errs):.2f} mm)"
                if errs else "")
        print(f"{kind:13s} n {len(v):3d}  IoU {np.mean(v) if v else float('nan'):.3f}  typed {typed}{disp}")
    if a.out is not None:
        a.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
