"""Object cancel from detected regions over every labelled multi-object plate of the shared G-code (issue 21).

For every object of every file in the folder whose labels name two or more objects, failures are put
on that object (foreign body, spaghetti, infill and thin-wall gaps, the object alone coming off the
bed) at a few onsets; the simulated photos are judged by the recommended pipeline and policy and the
first stopping decision is carried out by the action executor (:mod:`layerwatch.evaluate.object_cancel`).
Prints the outcomes per plate and per kind and every fall-back to pause with its reason.
Target: 0 wrong-object cancels; most cases cancel the failed object.

Run: ``python benchmarks/object_cancel.py [--onsets 0.3 0.6] [--seed 0] [-j 1] [-o table.md]``
(about 180 cases; ``--onsets 0.3 --interleave``: 89 cases, 22 minutes on one process of the loaded 2-core machine). Exit 1 when any case cancelled another object.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from layerwatch.evaluate.object_cancel import (
    CANCEL_KINDS,
    find_plates,
    iter_cases,
    plate_cases,
    summary_table,
    tally,
)

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "gcode"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gcode-dir", type=Path, default=DATA)
    ap.add_argument("--kinds", nargs="+", default=list(CANCEL_KINDS), choices=list(CANCEL_KINDS))
    ap.add_argument("--onsets", nargs="+", type=float, default=[0.3, 0.6], help="fractions of the object's layers")
    ap.add_argument("--plates", nargs="+", help="file names of the folder to take (default: every labelled plate)")
    ap.add_argument("--interleave", action="store_true",
                    help="run the cases round-robin over plates and kinds (a stopped run still covers each)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", default="1280x720", help="photo size WxH")
    ap.add_argument("-j", "--workers", type=int, default=1, help="processes (0: every core)")
    ap.add_argument("-o", "--out", type=Path, help="write the markdown table here too")
    a = ap.parse_args()
    if not a.gcode_dir.is_dir():
        print(f"no G-code folder {a.gcode_dir}; pass --gcode-dir", file=sys.stderr)
        return 2
    if any(not 0.0 <= q <= 1.0 for q in a.onsets):
        print("--onsets are fractions in [0, 1]", file=sys.stderr)
        return 2
    try:
        w, h = (int(v) for v in a.size.lower().split("x"))
    except ValueError:
        print(f"--size {a.size!r}: use WxH, e.g. 1280x720", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    plates = find_plates(a.gcode_dir, a.plates)
    per_plate, notes = [], []
    for name, (tp, om) in plates.items():
        c, n = plate_cases(name, tp, om, kinds=a.kinds, onsets=a.onsets, seed=a.seed)
        per_plate.append(c)
        notes += n
    if a.interleave:  # plate by plate, kind by kind, round-robin
        queues = [[c for c in cs if c.failure.type == k] for k in a.kinds for cs in per_plate]
        cases = [q[i] for i in range(max(map(len, queues), default=0)) for q in queues if i < len(q)]
    else:
        cases = [c for cs in per_plate for c in cs]
    print(f"{len(plates)} labelled multi-object plates: {', '.join(plates)}; {len(cases)} cases", flush=True)
    results = []
    for r in iter_cases(cases, plates, image_size=(w, h), seed=a.seed, workers=a.workers):
        results.append(r)
        print(f"[{len(results)}/{len(cases)}] {r.case.label}: {r.outcome} {r.cancelled} L{r.layer} "
              f"({r.seconds:.0f} s) {r.reason if r.outcome != 'correct' else ''}", flush=True)
    table = summary_table(results)
    counts = tally(results)
    text = (f"{table}\n\nleft out: " + ("; ".join(notes) if notes else "nothing") +
            f"\n\n{len(results)} cases, {counts['correct']} correct, {counts['pause']} paused instead, "
            f"{counts['wrong']} wrong-object cancels, {counts['early']} early, {counts['missed']} missed; "
            f"{time.perf_counter() - t0:.0f} s")
    print(text)
    if a.out is not None:
        a.out.write_text(text + "\n", encoding="utf-8")
    return 1 if counts["wrong"] else 0


if __name__ == "__main__":
    sys.exit(main())
