"""What does the failure typing say against a baseline typer? Both typers on the evaluation's own photos, in one run.

Run: ``python benchmarks/typing_equivalence.py [--rev 2dc419e] [--layers 200] [--beside-share 0.3]``.

The evaluation of ``layerwatch evaluate`` (:func:`~layerwatch.evaluate.harness.run_evaluation`:
the bundled example part, recommended settings, 1280 x 720 simulated photos, seed 0, single-photo
and series modes) runs once. Every call of the current
:meth:`~layerwatch.analysis.failure_typing.FailureTyper.type_result` also runs
the typer of ``--rev`` (the whole package of that revision loaded in this process with
``git archive``, ``benchmarks/baseline_revision.py``, so its typer registers the part with its
own registration) on a copy of the same layer result, with its own memory
of the previous photo, and each is timed by the process's CPU time. Then:

* the per-region agreement of the kinds (and the largest difference of
  confidence and displacement); a typer changed on purpose shows here as changed,
* :func:`~layerwatch.evaluate.modes.summarize_modes` of both (confusion
  matrix, IoU per type, share of layer-shift / detachment displacements within 0.5 mm)
  on the same photos and the same truth,
* the median typing time per typed layer of both.

Baselines: ``2dc419e`` (default) is the typer before issue 18's localisation work (moved
parts reported as their blocks, phase correlation only); ``74c3e36`` the typer before
issue 18's typing speed work (kinds, confidences and displacements then agreed on every region).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import copy  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from baseline_revision import load_revision  # noqa: E402

import layerwatch.evaluate.harness as harness  # noqa: E402
from layerwatch.analysis import failure_typing  # noqa: E402
from layerwatch.evaluate.modes import MODES, summarize_modes  # noqa: E402
from layerwatch.examples import PART_CONFIG, PART_GCODE  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.pipeline.config import resolve_config  # noqa: E402
from layerwatch.simulate import default_camera  # noqa: E402

OLD_MODULE = "layerwatch.analysis.failure_typing"


class _Shadow:
    """Runs the old typer beside each current one and keeps what both said."""

    def __init__(self, old_cls) -> None:
        self.old_cls = old_cls
        self.typers: dict[int, object] = {}  # current typer id -> its old twin
        self.old_results: dict[int, object] = {}  # id of a current result -> the old typer's copy of it
        self.pairs: list[tuple] = []  # (old kind, new kind, |conf diff|, displacement diff mm or None)
        self.ms: dict[str, list[float]] = {"old": [], "new": []}

    def install(self) -> None:
        cur = failure_typing.FailureTyper
        type_result, reset, shadow = cur.type_result, cur.reset, self

        def both(typer, res, top_bgr, top, reference, footprint, valid=None):
            twin = shadow.typers.setdefault(id(typer), shadow.old_cls(typer.toolpath, typer.topview))
            twin_res = copy.deepcopy(res)
            c = time.process_time()
            twin.type_result(twin_res, top_bgr, top, reference, footprint, valid)
            t_old = time.process_time() - c
            c = time.process_time()
            out = type_result(typer, res, top_bgr, top, reference, footprint, valid)
            t_new = time.process_time() - c
            shadow.old_results[id(res)] = twin_res
            if res.regions or res.outside_regions:
                shadow.ms["old"].append(t_old * 1e3)
                shadow.ms["new"].append(t_new * 1e3)
            for a, b in zip([*twin_res.regions, *twin_res.outside_regions], [*res.regions, *res.outside_regions],
                            strict=True):
                dd = None
                if a.displacement_mm is not None and b.displacement_mm is not None:
                    dd = float(np.hypot(*(np.subtract(a.displacement_mm, b.displacement_mm))))
                elif (a.displacement_mm is None) != (b.displacement_mm is None):
                    dd = float("inf")
                shadow.pairs.append((a.kind, b.kind, abs(a.kind_confidence - b.kind_confidence), dd))
            return out

        def both_reset(typer):
            reset(typer)
            if id(typer) in shadow.typers:
                shadow.typers[id(typer)].reset()

        cur.type_result, cur.reset = both, both_reset

        score = harness.mode_score

        def both_scores(res, truth, topview, true_offset_mm=None):
            new = score(res, truth, topview, true_offset_mm)
            old_res = shadow.old_results.pop(id(res), None)
            new.old = score(old_res, truth, topview, true_offset_mm) if old_res is not None else new
            return new

        harness.mode_score = both_scores


def _before(records: list) -> list:
    """The records with each mode's score as the old typer's."""
    return [dataclasses.replace(r, modes={m: s.old for m, s in r.modes.items()}) for r in records]


def _confusion(summary: dict) -> str:
    lines = []
    for mode, s in summary.items():
        lines.append(f"  {mode}:")
        cols = [k for k in s["kinds"] if any(s["confusion"][t][k] for t in s["confusion"])]
        lines.append("    " + " " * 14 + " ".join(f"{k[:11]:>11}" for k in cols))
        for t, row in s["confusion"].items():
            lines.append(f"    {t:>14}" + " ".join(f"{row[k]:11d}" for k in cols))
        for t, errs in s["displacement"].items():
            e = np.asarray(errs)
            within = f"{int((e <= 0.5).sum())}/{len(e)}" if len(e) else "0/0"
            med = f"{float(np.median(e)):.2f}" if len(e) else "-"
            lines.append(f"    {t} displacement within 0.5 mm: {within} (median error {med} mm)")
        lines.append("    IoU (failures >= 5 mm; every shift and detachment): "
                     + ", ".join(f"{t} {v:.2f} (n {k})" for t, (v, k) in s["iou"].items()))
    return "\n".join(lines)


def run(rev: str, layers: int, beside: float, seed: int = 0) -> None:
    cv2.setNumThreads(1)
    old = load_revision(rev, [OLD_MODULE])
    if old is None:
        raise SystemExit(f"revision {rev} cannot be extracted (git archive failed)")
    assert old[OLD_MODULE].__file__ != failure_typing.__file__, "the baseline is the current code"
    shadow = _Shadow(old[OLD_MODULE].FailureTyper)
    shadow.install()
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG, recommended=True).config
    cam = default_camera(cfg.topview.topview(), image_size=(1280, 720))
    t0 = time.perf_counter()
    data = harness.run_evaluation(tp, cfg, cam, n_layers=layers, seed=seed, beside_share=beside, modes=MODES)
    after = summarize_modes(data.records, 5.0)
    before = summarize_modes(_before(data.records), 5.0)
    n = len(shadow.pairs)
    agree = sum(a == b for a, b, _, _ in shadow.pairs)
    flips = Counter((a, b) for a, b, _, _ in shadow.pairs if a != b)
    dconf = max((c for _, _, c, _ in shadow.pairs), default=0.0)
    ddisp = max((d for *_, d in shadow.pairs if d is not None), default=0.0)
    failed = [r for r in data.records if r.kind != "clean"]
    same_kind = {m: sum(r.modes[m].kind == r.modes[m].old.kind for r in failed) for m in MODES}
    print(f"evaluation: {len(data.records)} photos ({len(failed)} failed) of {data.setup['n_scenarios']} prints, "
          f"1280x720, seed {seed}, beside share {beside}, modes {', '.join(MODES)}; {time.perf_counter() - t0:.0f} s; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"typed regions (both modes): {n}; kinds agree {agree}/{n} ({100 * agree / max(n, 1):.1f} %)"
          f"{'; differing: ' + ', '.join(f'{a}->{b} x{k}' for (a, b), k in flips.items()) if flips else ''}")
    print(f"  largest |confidence difference| {dconf:.3f}, largest displacement difference {ddisp:.3f} mm")
    print("  kind of the region covering the failure, same before and after: "
          + ", ".join(f"{m} {same_kind[m]}/{len(failed)}" for m in MODES))
    o, c = np.asarray(shadow.ms["old"]), np.asarray(shadow.ms["new"])
    print(f"typing per typed layer, CPU ms (one thread), median / 90th percentile / max: "
          f"before {np.median(o):.1f} / {np.percentile(o, 90):.1f} / {o.max():.1f}, "
          f"after {np.median(c):.1f} / {np.percentile(c, 90):.1f} / {c.max():.1f} ({len(c)} typed layers)")
    print(f"before ({rev}):\n{_confusion(before)}")
    print(f"after (current):\n{_confusion(after)}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", default="2dc419e", help="git revision of the typer compared against")
    ap.add_argument("--layers", type=int, default=200, help="approximate number of simulated photos")
    ap.add_argument("--beside-share", type=float, default=0.3, help="share of objects/strands beside the part")
    args = ap.parse_args(argv)
    run(args.rev, args.layers, args.beside_share)


if __name__ == "__main__":
    main()
