"""Rates of the empty-bed check, the first-layer inspection and the nothing-extruded check (issue 21).

Counts over simulated cases (:mod:`layerwatch.evaluate.checks`): leftover objects of 10-40 mm caught
and false holds over clean starts under changed light, on four bed/filament variants; nothing-extruded
runs caught within two layers and false alarms over every layer of clean prints (the example part, a 12 mm
cube, a 20 mm box and the simulator's window part: a window, a bridge, thin walls); first-layer verdicts.
Targets: >= 97 % of objects caught, 0 false holds over >= 200 clean starts; >= 97 % of nothing-extruded
runs caught within 2 layers, 0 false alarms.

Run: ``python benchmarks/eval_checks.py [--clean 200 --objects 200 --runs 160 --first 24 --seed 1]``
(about 15 minutes on one core; ``--clean 0 --objects 0 --first 0``: the nothing-extruded trials alone, a few
minutes; ``--width``: their photos' width, 1280 by default, as the thresholds were chosen; ``--baseline`` judges the same nothing-extruded photos also with the parallax rule off, the check as
it was before it).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from layerwatch.analysis.check_settings import ExtrusionSettings
from layerwatch.evaluate.checks import (
    bed_check_trials,
    extrusion_trials_compared,
    first_layer_trials,
)
from layerwatch.examples import PART_GCODE
from layerwatch.simulate.parts import window_part

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "gcode"
PRINTS = [PART_GCODE, DATA / "prusaslicer-2.8.1_mini-cube_ascii.gcode", DATA / "miraclegrue_20mm-box.gcode"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clean", type=int, default=200)
    ap.add_argument("--objects", type=int, default=200)
    ap.add_argument("--runs", type=int, default=160, help="nothing-extruded runs (cycling through the 4 prints)")
    ap.add_argument("--first", type=int, default=24)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--clean-prints", type=int, default=2, help="clean prints (seeds) per G-code")
    ap.add_argument("--width", type=int, default=1280,
                    help="photo width px of the nothing-extruded trials (16:9; the thresholds were chosen at 1280)")
    ap.add_argument("--baseline", action="store_true",
                    help="judge the same nothing-extruded photos also with the parallax rule off "
                         "([extrusion] still_similarity = 1: the check before it)")
    a = ap.parse_args()
    if not 160 <= a.width <= 8192:
        ap.error("--width must be in [160, 8192] px")
    t = time.perf_counter()
    false, caught = bed_check_trials(PART_GCODE, a.clean, a.objects, a.seed)
    print(false.line("empty bed: false holds over clean starts (light changed)"))
    print(caught.line("empty bed: leftover objects >= 10 mm caught"))
    print(f"  ({time.perf_counter() - t:.0f} s)", flush=True)
    t = time.perf_counter()
    prints = [*(p for p in PRINTS if Path(p).is_file()), window_part()]
    variants = {"": ExtrusionSettings(enabled=True)}
    if a.baseline:
        variants[" (parallax rule off)"] = ExtrusionSettings(enabled=True, still_similarity=1.0)
    results = extrusion_trials_compared(prints, a.runs, list(variants.values()), a.seed, clean_prints=a.clean_prints,
                                        size=(a.width, a.width * 9 // 16))
    for tag, (caught, false) in zip(variants, results, strict=True):
        print(caught.line(f"nothing extruded{tag}: runs caught within 2 layers"))
        print(false.line(f"nothing extruded{tag}: false alarms over clean layers"))
        for name, c in (("clean layers", false), ("second layer of a run", caught)):
            v = np.asarray(c.values, float)
            judged = v[np.isfinite(v)]
            q = np.percentile(judged, [0, 5, 50, 95, 100]).round(3).tolist() if judged.size else []
            print(f"  similarity on {name}: {judged.size}/{v.size} judged; min, 5 %, median, 95 %, max = {q}")
    print(f"  ({time.perf_counter() - t:.0f} s)", flush=True)
    t = time.perf_counter()
    for case, c in first_layer_trials(PART_GCODE, a.first, a.seed).items():
        what = "false fails" if case == "clean" else "caught"
        print(c.line(f"first layer, {case}: {what}"))
    print(f"  ({time.perf_counter() - t:.0f} s)")


if __name__ == "__main__":
    main()
