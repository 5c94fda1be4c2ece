"""Issue 18 study: do thresholds learned from a job's own first clean layers beat fixed ones?

Run: ``python tools/study_self_calibration.py [--jobs-per-look 6] [--width 1280] [--calib 4]``.

Jobs: simulated prints of the bundled example part under six *looks*
(filament and bed colour, light, exposure: the default orange on a dark bed,
white, black in dim light, blue over-exposed, grey on a light bed, green in a
hard light), each look with one job per failure type (random onset after the
calibration layers, random size and place) and one clean job. Every layer
of a job goes through the recommended per-layer step in order (series mode,
the scene channel on), so the first layers are what a monitor would see.

The first ``--calib`` analysed layers (after ``skip_first_layers``) are the
job's calibration layers (clean in every job: the onsets come later). From
them each job learns:

* ``ratio``: a pause ratio ``mean + 3 sd`` of their a% at T_S 0.20, either
  free (floored at 0.5 %) or only ever raised above the fixed 2.5 %;
* ``T_S``: a similarity threshold: the 0.25th percentile of the similarities
  of their considered blocks, capped to [0.05, 0.30] (fixed: 0.20), a% then
  counted at it.

Scores (later layers only; a% from each layer's heatmap, the same count for
every scorer: anomalous considered blocks x tile area / printed area):
``fixed`` (a% at T_S 0.20), ``learned ratio`` (a% minus the job's learned
pause ratio), ``learned T_S`` (a% at the job's threshold). Reported: the
AUROC of each score per failure type against the clean layers pooled over
all looks (a per-job threshold only matters across jobs), per look, and at
the operating point (fixed: a% > 2.5 %; learned: a% above the job's ratio, or
a% at the job's T_S > 2.5 %) the share of clean layers
alarmed and of failed layers (from the onset) detected.
"""

from __future__ import annotations

import argparse
import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from layerwatch.evaluate.stats import roc_auc  # noqa: E402
from layerwatch.examples import PART_CONFIG, PART_GCODE  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.pipeline.config import recommended_config  # noqa: E402
from layerwatch.pipeline.step import LayerPipeline  # noqa: E402
from layerwatch.simulate import FAILURE_TYPES, PrintSimulator, SimSettings, default_camera  # noqa: E402
from layerwatch.simulate.failures import random_scenarios, with_onset  # noqa: E402

LOOKS = {
    "orange, dark bed": {},
    "white": {"filament_rgb": (0.88, 0.88, 0.85)},
    "black, dim": {"filament_rgb": (0.07, 0.07, 0.08), "light_intensity": 0.55, "ambient": 0.1},
    "blue, over-exposed": {"filament_rgb": (0.12, 0.25, 0.75), "exposure": 1.5},
    "grey, light bed": {"filament_rgb": (0.5, 0.5, 0.5), "bed_rgb": (0.55, 0.5, 0.45), "light_intensity": 0.7},
    "green, hard light": {"filament_rgb": (0.15, 0.6, 0.2), "light_intensity": 1.3, "ambient": 0.05, "fill": 0.08},
}
FIXED_T, FIXED_RATIO, RATIO_FLOOR = 0.20, 0.025, 0.005


def a_at(res, t: float) -> float:
    """a% of one analysed layer counted at similarity threshold ``t`` from its heatmap."""
    if res.heatmap is None or res.mask is None or res.printed_area_mm2 <= 0:
        return 0.0
    n = int(np.count_nonzero(res.mask & (res.heatmap < t)))
    return min(1.0, n * res.grid.tile_area_mm2 / res.printed_area_mm2)


def run_job(tp, cfg, cam, tv, look: dict, scen, seed: int, last: int) -> list:
    """Results of layers 1..last of one simulated job, in order."""
    sim = PrintSimulator(tp, cam, tv, scen, seed=seed, settings=SimSettings(**look))
    pipe = LayerPipeline(tp, cam, cfg, memo=4)
    pipe.new_print(sim.bed_photo())
    out = []
    for i in range(0, last + 1):
        fr = sim.frame(i)
        res = pipe.process(fr.photo, i)
        kind = fr.meta["failures"][0] if fr.meta.get("failures") else "clean"
        out.append((i, kind, res))
    return out


def learn(calib: list) -> tuple[float, float]:
    """(``mean + 3 sd`` of a% at the fixed T_S, learned T_S) from the calibration layers' results."""
    a = np.array([a_at(r, FIXED_T) for r in calib])
    spread = float(a.mean() + 3 * a.std())
    sims = np.concatenate([r.heatmap[r.mask] for r in calib if r.heatmap is not None and r.mask is not None])
    t = float(np.clip(np.percentile(sims, 0.25), 0.05, 0.30)) if sims.size else FIXED_T
    return spread, t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--calib", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-onset", type=int, default=16)
    ap.add_argument("--looks", type=int, default=len(LOOKS), help="the first N looks only")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    tp = read_toolpath(PART_GCODE)
    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    cam = default_camera(tv, image_size=(args.width, int(round(args.width * 9 / 16))))
    first = cfg.policy.skip_first_layers
    lo = first + args.calib + 1
    rng = np.random.default_rng(args.seed)
    rows = []  # (look, kind, layers since onset, scores per scorer, alarms per scorer)
    for li, (look_name, look) in enumerate(list(LOOKS.items())[: args.looks]):
        for ti, kind in enumerate((*FAILURE_TYPES, "clean")):
            seed = args.seed * 1000 + li * 10 + ti
            if kind == "clean":
                scen, onset = [], args.max_onset - 2
            else:
                f = random_scenarios(tp, 1, seed=seed, types=(kind,), clean_fraction=0.0)[0].failures[0]
                onset = int(rng.integers(lo, args.max_onset + 1))
                scen = [with_onset(f, onset)]
            results = run_job(tp, cfg, cam, tv, look, scen, seed, min(onset + 3, tp.n_layers - 1))
            ok = [(i, k, r) for i, k, r in results if i >= first and r.status == "ok"]
            calib, rest = ok[: args.calib], ok[args.calib:]
            spread, t = learn([r for _, _, r in calib])
            free, raised = max(RATIO_FLOOR, spread), max(FIXED_RATIO, spread)
            for i, k, r in rest:
                a0, at = a_at(r, FIXED_T), a_at(r, t)
                since = i - onset if k != "clean" else -1
                rows.append((look_name, k, since, (a0, a0 - free, a0 - raised, at),
                             (a0 > FIXED_RATIO, a0 > free, a0 > raised, at > FIXED_RATIO)))
            print(f"{look_name:20s} {kind:14s} onset {onset:2d} mean+3sd {100 * spread:5.2f} % T_S {t:.3f}; "
                  f"a% calib {[round(100 * a_at(r, FIXED_T), 2) for _, _, r in calib]}", flush=True)
    report(rows)


def report(rows: list) -> None:
    kinds = np.array([r[1] for r in rows])
    S = np.array([r[3] for r in rows])
    A = np.array([r[4] for r in rows])
    clean = kinds == "clean"
    names = ("fixed (T_S 0.20, pause 2.5 %)", "learned pause ratio", "learned ratio, only raised", "learned T_S")
    types = [t for t in FAILURE_TYPES if (kinds == t).any()]
    print(f"\n{int(clean.sum())} clean and {int((~clean).sum())} failed layers after calibration, "
          f"{len(set(r[0] for r in rows))} looks\n")
    print("| scorer | " + " | ".join(types) + " | clean layers alarmed | failed layers detected |")
    print("|---" * (len(types) + 3) + "|")
    for j, name in enumerate(names):
        aucs = [roc_auc(S[kinds == t, j], S[clean, j]) for t in types]
        print(f"| {name} | " + " | ".join(f"{v:.3f}" for v in aucs)
              + f" | {A[clean, j].mean():.3f} | {A[~clean, j].mean():.3f} |")
    looks = sorted({r[0] for r in rows})
    print("\nper look, AUROC over all types (failed vs clean of the same look):\n")
    print("| look | " + " | ".join(names) + " |")
    print("|---" * (len(names) + 1) + "|")
    lk = np.array([r[0] for r in rows])
    for look in looks:
        sel = lk == look
        vals = [roc_auc(S[sel & ~clean, j], S[sel & clean, j]) for j in range(len(names))]
        print(f"| {look} | " + " | ".join(f"{v:.3f}" for v in vals) + " |")
    print("\npooled over looks, AUROC of all failed vs all clean layers: "
          + ", ".join(f"{n} {roc_auc(S[~clean, j], S[clean, j]):.3f}" for j, n in enumerate(names)))


if __name__ == "__main__":
    main()
