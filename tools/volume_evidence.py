"""Clean prints judged with the height-map and with the occupancy-volume reference (issue 18).

For each part (``window_part``: a bridge, a hollow box with a window, an
overhang; the bundled example part) and each ``render.reference``, whole
clean prints are simulated and judged by the harness's
:func:`~layerwatch.evaluate.harness.clean_false_alarms` with the recommended
setting (jaccard, T_S 0.20, pause a% > 2.5 % on two layers) and with a
footprint margin (the whole-view direction of the issue): layers, single-layer
alarms, the policy's notices and pauses, max and mean clean a%. The same
photos (same seeds) are judged with both references. Then, on one clean print
of ``window_part``, the blocks of the whole view where the two references
differ: which one the photo matches there.

Run::

    PYTHONPATH=src python tools/volume_evidence.py [--prints N] [--example-layers N] [--gcode FILE ...]
        [--margins MM ...] [--detection N] [--out table.md]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from layerwatch.evaluate.harness import clean_false_alarms, run_evaluation, tile_fraction  # noqa: E402
from layerwatch.evaluate.summary import at_setting  # noqa: E402
from layerwatch.examples import PART_CONFIG, PART_GCODE  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.pipeline.config import resolve_config  # noqa: E402
from layerwatch.pipeline.step import LayerPipeline  # noqa: E402
from layerwatch.simulate import PrintSimulator, default_camera  # noqa: E402
from layerwatch.simulate.parts import window_part  # noqa: E402


def judge(name, tp, cfg, n_layers, seed, margins):
    cam = default_camera(cfg.topview.topview())
    rows = []
    for margin, ref in ((m, r) for m in margins for r in ("height", "volume")):
        c = cfg.model_copy(update={"render": cfg.render.model_copy(update={"reference": ref}),
                                   "analysis": cfg.analysis.model_copy(update={"footprint_margin_mm": margin})})
        t = time.perf_counter()
        r = clean_false_alarms(tp, c, cam, n_layers, float(c.policy.pause_ratio),
                               consecutive=c.policy.consecutive_layers, seed=seed)
        a = np.asarray(r["a"])
        rows.append((name, ref, margin, r["layers"], r["prints"], r["layer_alarms"], r["policy_alarms"], r["pauses"],
                     100 * r["max_a"], 100 * float(a.mean()) if a.size else float("nan"),
                     100 * float(np.percentile(a, 99)) if a.size else float("nan"), time.perf_counter() - t))
        print(" | ".join(str(v if not isinstance(v, float) else round(v, 2)) for v in rows[-1]), flush=True)
    return rows


def differing_blocks(tp, cfg, seed, min_share=0.25, grey=20):
    """On the blocks where the two references differ, how well does each match the clean photo?

    Every block of the whole view (not only the footprint) whose tile has at
    least ``min_share`` of pixels where the height-map and volume references
    differ by more than ``grey`` levels is compared: mean similarity (the
    configured measure) of the photo's top view with each reference, and the
    share of those blocks below T_S (anomalous, were they considered).
    """
    cam = default_camera(cfg.topview.topview())
    pipes = {ref: LayerPipeline(tp, cam, cfg.model_copy(update={
        "render": cfg.render.model_copy(update={"reference": ref})}), memo=2) for ref in ("height", "volume")}
    sim = PrintSimulator(tp, cam, cfg.topview.topview(), (), seed=seed)
    sims = {"height": [], "volume": []}
    for i in range(tp.n_layers):
        photo = sim.frame(i).photo
        res = {ref: p.process(photo, i) for ref, p in pipes.items()}
        if any(r.status != "ok" or r.heatmap is None for r in res.values()):
            continue
        diff = np.abs(pipes["height"].reference(i).image.astype(int) - pipes["volume"].reference(i).image) > grey
        g = res["height"].grid
        n, m = res["height"].heatmap.shape
        sel = tile_fraction(diff, n, m, g.cell_px, g.block_cells) >= min_share
        for ref, r in res.items():
            sims[ref].append(np.asarray(r.heatmap)[sel])
    out = {}
    for ref, v in sims.items():
        a = np.concatenate(v) if v else np.zeros(0)
        out[ref] = (a.size, float(a.mean()) if a.size else float("nan"),
                    100 * float((a < cfg.analysis.threshold).mean()) if a.size else float("nan"))
    return out


def detection(name, tp, cfg, n_layers, seed):
    """Simulated failures judged with both references: AUROC and IoU per type at the configured setting."""
    cam = default_camera(cfg.topview.topview())
    lines = []
    for ref in ("height", "volume"):
        c = cfg.model_copy(update={"render": cfg.render.model_copy(update={"reference": ref})})
        data = run_evaluation(tp, c, cam, n_layers=n_layers, seed=seed)
        got = at_setting(data, c.analysis.metric, c.analysis.threshold, c.policy.pause_ratio)
        if got is None:
            continue
        cells = [f"{t} {v[1]:.2f} / {v[3]:.2f}" for t, v in got["types"].items()]
        lines.append(f"| {name} | {ref} | {got['clean_above']}/{got['n_clean']} | {100 * got['max_clean']:.2f} | "
                     + "; ".join(cells) + " |")
        print(lines[-1], flush=True)
    return lines


def _blocks_lines(name, tp, cfg, seed):
    blocks = differing_blocks(tp, cfg, seed)
    lines = ["", f"{name}, one clean print (seed {seed}), whole view: blocks where the two references differ "
             f"({cfg.analysis.metric}, T_S {cfg.analysis.threshold:.2f})", "",
             "| reference | blocks | mean similarity with the photo | blocks below T_S |", "|---|---|---|---|"]
    return lines + [f"| {ref} | {n} | {mean:.3f} | {below:.1f} % |" for ref, (n, mean, below) in blocks.items()]


def _parts(args):
    """``(name, toolpath, config, clean layers)`` of the parts asked for."""
    parts = []
    if args.prints:
        tp = window_part()  # recommended setting, observed square centred on the part (0, 0)
        parts.append(("window_part", tp, resolve_config(None).config, args.prints * tp.n_layers))
    if args.example_layers:
        parts.append(("example part", read_toolpath(PART_GCODE), resolve_config(PART_CONFIG).config,
                      args.example_layers))
    for path in args.gcode:  # a slicer file: the observed square centred on its part, one print
        tp = read_toolpath(path)
        x0, y0, x1, y1 = tp.bounds
        cfg = resolve_config(None, gcode={"topview": {"center_mm": ((x0 + x1) / 2, (y0 + y1) / 2)}}).config
        parts.append((path.name, tp, cfg, tp.n_layers))
    return parts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--prints", type=int, default=3, help="clean prints of window_part per reference (0: skip it)")
    ap.add_argument("--example-layers", type=int, default=0, help="layers of the example part (0: skip)")
    ap.add_argument("--gcode", type=Path, nargs="*", default=[], help="slicer files to add (one clean print each)")
    ap.add_argument("--margins", type=float, nargs="+", default=[0.0, 5.0],
                    help="footprint_margin_mm values (0: the recommended footprint-only analysis)")
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--detection", type=int, default=0,
                    help="also simulate about N photos with failures per part and reference (0: skip)")
    ap.add_argument("--out", type=Path, default=None, help="write the Markdown table here")
    args = ap.parse_args()
    parts = _parts(args)
    rows = [r for name, tp, cfg, n in parts for r in judge(name, tp, cfg, n, args.seed, args.margins)]
    head = ("| part | reference | margin mm | clean layers | prints | single-layer alarms (a% > 2.5 %) | policy notices/pauses "
            "| pauses | max a% | mean a% | 99th pct a% | seconds |\n|" + "---|" * 12)
    lines = [head] + ["| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in r) + " |"
                      for r in rows]
    for name, tp, cfg, _ in parts:
        if name != "example part":  # nothing differs much there
            lines += _blocks_lines(name, tp, cfg, args.seed)
    if args.detection:
        lines += ["", f"Simulated failures (about {args.detection} photos per part and reference, seed 0), configured "
                  "setting: clean layers above the pause ratio, max clean a%, per type AUROC / mean IoU (>= 5 mm)",
                  "", "| part | reference | clean above | max clean a% | AUROC / IoU per type |", "|---|---|---|---|---|"]
        for name, tp, cfg, _ in parts:
            lines += detection(name, tp, cfg, args.detection, 0)
    print("\n".join(lines))
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
