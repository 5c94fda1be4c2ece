"""Issue 18 study: single-layer alarms and policy alerts on whole clean prints, a% with whole tiles and with printed shares.

Run: ``PYTHONPATH=<src> python tools/study_clean_alarms.py --part window --seeds 1100-1110 [--dump DIR] [--out runs.json]``.

Each print goes through the code path of the report's clean prints
(:func:`~layerwatch.evaluate.harness.clean_false_alarms`: the simulator with
the print's seed, one :class:`~layerwatch.pipeline.step.LayerPipeline` per
print in series mode with the empty-bed photo, the recommended settings of the
bundled example's job, 1280 x 720 photos, the policy with pause a% > 2.5 % on
two layers). The report gives the window part's print ``k`` the seed
``100 + 1000 + k`` (1100-1110) and the example part's ``100 + k`` (100-167).

Every layer's result is scored twice, each with its own
:class:`~layerwatch.pipeline.policy.PausePolicy`: as the pipeline gives it
(``[analysis] anomalous_area`` as configured) and with every anomalous block
counting its whole tile (the paper, ``"tiles"``; what main did before
``"printed"``): the same photos, the same blocks, so the two columns differ
only in what S_A counts. Printed per print: the alarm layers (a% above the
pause ratio, from layer ``skip_first_layers``), those of them that also have
the minimum area (the policy's and the report's test,
:func:`~layerwatch.pipeline.policy.layer_alarm`), the policy's notify/pause
layers, the pauses and the highest a%. ``--dump`` writes, for every layer that
alarms either way, the photo's top view, the reference and the overlay (PNG) and the
block heatmap, considered mask and footprint (``.npz``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import copy  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from layerwatch.analysis.overlay import overlay_image  # noqa: E402
from layerwatch.analysis.result import LayerResult  # noqa: E402
from layerwatch.analysis.scoring import anomaly_ratio  # noqa: E402
from layerwatch.examples import PART_CONFIG, PART_GCODE  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.pipeline.config import resolve_config  # noqa: E402
from layerwatch.pipeline.policy import PausePolicy, layer_alarm  # noqa: E402
from layerwatch.pipeline.step import LayerPipeline  # noqa: E402
from layerwatch.simulate import PrintSimulator, default_camera  # noqa: E402
from layerwatch.simulate.parts import window_part  # noqa: E402


def _seeds(text: str) -> list[int]:
    """``"1100-1110"`` or ``"5,7,9"``."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def _whole_tiles(res: LayerResult, tile_mm2: float) -> LayerResult:
    """``res`` as S_A counting every anomalous block's whole tile (plus what the changed-as-predicted channel added)."""
    if res.status != "ok":
        return res
    r = copy.copy(res)
    added = float(res.layer_change.added_mm2) if res.layer_change is not None else 0.0
    r.anomalous_area_mm2 = res.n_anomalous * tile_mm2 + added
    r.uncounted_mm2 = 0.0
    r.anomaly_ratio = anomaly_ratio(1, r.anomalous_area_mm2, float(res.printed_area_mm2))
    return r


def run_print(part: str, seed: int, dump: Path | None = None, area: str | None = None) -> dict:
    """One whole clean print of ``part`` (``"window"`` or ``"example"``) scored both ways; see the module notes.

    ``area`` sets ``[analysis] anomalous_area`` (``None``: as the bundled job resolves it).
    """
    flags = {"analysis": {"anomalous_area": area}} if area else None
    cfg = resolve_config(PART_CONFIG, flags=flags).config
    cam = default_camera(cfg.topview.topview(), image_size=(1280, 720))
    cfg = cfg.for_camera(cam)
    tv = cfg.topview.topview()
    tp = (window_part(center=(float(cfg.topview.center_mm[0]), float(cfg.topview.center_mm[1])))
          if part == "window" else read_toolpath(PART_GCODE))
    ps = cfg.policy
    tile_mm2 = (cfg.analysis.cell_px / tv.px_per_mm) ** 2
    pipe = LayerPipeline(tp, cam, cfg, memo=tp.n_layers)
    sim = PrintSimulator(tp, cam, tv, (), seed=seed)
    pipe.new_print(sim.bed_photo() if pipe.scene is not None else None)
    modes = {"configured": PausePolicy(ps), "tiles": PausePolicy(ps)}
    out = {m: {"alarms": [], "area_alarms": [], "alerts": [], "pauses": 0, "max_a": 0.0} for m in modes}
    beside: list[list[float]] = []  # the scene channel's change beside the print: [layer, mm^2] where any
    stopped = dict.fromkeys(modes, False)
    for i in range(tp.n_layers):
        res = pipe.process(sim.frame(i).photo, i)
        if res.status == "ok" and res.outside_anomalous_mm2 > 0:
            beside.append([i, round(float(res.outside_anomalous_mm2), 1)])
        for mode, policy in modes.items():
            r = res if mode == "configured" else _whole_tiles(res, tile_mm2)
            decision = policy.update(r)
            if r.status != "ok":
                continue
            k, a = out[mode], float(r.anomaly_ratio)
            k["max_a"] = max(k["max_a"], round(100 * a, 2))
            if r.layer >= ps.skip_first_layers and a > ps.pause_ratio:
                k["alarms"].append(i)
                if layer_alarm(a, float(r.anomalous_area_mm2) + float(r.uncounted_mm2), ps):
                    k["area_alarms"].append(i)  # the policy's and the report's test (enough mm^2 too)
                if dump is not None and not (dump / f"{part}_{seed}_{i:03d}.npz").exists():
                    _dump(dump, f"{part}_{seed}_{i:03d}", pipe, res, tv)
            if not stopped[mode] and decision.action != "none":
                k["alerts"].append(i)
            if decision.stops and not stopped[mode]:
                k["pauses"] += 1
                stopped[mode] = True
    return {"part": part, "seed": seed, "layers": tp.n_layers, "beside": beside, **out}


def _dump(folder: Path, name: str, pipe: LayerPipeline, res: LayerResult, tv) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    ref = pipe.reference(res.layer)
    if pipe.last_top is None:
        return
    cv2.imwrite(str(folder / f"{name}_top.png"), pipe.last_top)
    cv2.imwrite(str(folder / f"{name}_ref.png"), ref.image)
    cv2.imwrite(str(folder / f"{name}_overlay.png"), overlay_image(pipe.last_top, res, tv, ref.footprint)[..., ::-1])
    np.savez_compressed(folder / f"{name}.npz", heat=res.heatmap, mask=res.mask, footprint=ref.footprint)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("window", "example"), default="window")
    ap.add_argument("--seeds", default="1100-1110", help="e.g. 1100-1110 or 100,111")
    ap.add_argument("--dump", type=Path, help="folder for the alarm layers' images and block maps")
    ap.add_argument("--out", type=Path, help="JSON of every print's counts")
    ap.add_argument("--anomalous-area", choices=("tiles", "part", "printed"),
                    help="[analysis] anomalous_area of the configured column (default: the job's)")
    args = ap.parse_args()
    runs = []
    for seed in _seeds(args.seeds):
        run = run_print(args.part, seed, args.dump, args.anomalous_area)
        runs.append(run)
        print(seed, " | ".join(f"{m}: alarms {run[m]['alarms']} (with min. area {run[m]['area_alarms']}) "
                               f"alerts {run[m]['alerts']} pauses {run[m]['pauses']} "
                               f"max a% {run[m]['max_a']:.2f}" for m in ("tiles", "configured")),
              f"| beside the print (layer, mm^2): {run['beside']}", flush=True)
    for m in ("tiles", "configured"):
        print(f"{m}: {sum(len(r[m]['alarms']) for r in runs)} single-layer alarms "
              f"({sum(len(r[m]['area_alarms']) for r in runs)} with the minimum area), "
              f"{sum(len(r[m]['alerts']) for r in runs)} policy alerts, {sum(r[m]['pauses'] for r in runs)} pauses "
              f"in {sum(r['layers'] for r in runs)} layers of {len(runs)} prints")
    print(f"layers with change beside the print: {sum(len(r['beside']) for r in runs)}, largest "
          f"{max((b[1] for r in runs for b in r['beside']), default=0.0):.1f} mm^2")
    if args.out is not None:
        args.out.write_text(json.dumps(runs, indent=1))


if __name__ == "__main__":
    main()
