"""Clean prints of the simulator's window part (windows, bridge, overhang): false alarms per print.

Run: ``python benchmarks/window_clean.py [--march plane|image] 1100 1101 ...`` (simulation seeds; the
report's clean prints of the window part use seeds 1100, 1101, ... with ``layerwatch evaluate``'s
default clean seed 100). Same configuration as ``layerwatch evaluate`` on the bundled example part
(recommended settings, 1280 x 720 photos); prints one line per seed and the totals. ``--march`` sets
``render.march`` (branch ``camref``); left out, the configuration's own.
"""

from __future__ import annotations

import sys
import time

from layerwatch.cli.pipeline import _toolpath, job_settings
from layerwatch.evaluate.harness import _clean_print
from layerwatch.simulate import default_camera
from layerwatch.simulate.parts import window_part


def main(argv: list[str]) -> int:
    march = None
    if argv[:1] == ["--march"]:
        march, argv = argv[1], argv[2:]
    seeds = [int(a) for a in argv] or list(range(1100, 1111))
    tp = _toolpath(None)
    cfg = job_settings(None, None, tp).config
    if march is not None:
        cfg = cfg.model_copy(update={"render": cfg.render.model_copy(update={"march": march})})
    width = 1280
    cam = default_camera(cfg.topview.topview(), image_size=(width, int(round(width * 9 / 16))))
    cfg = cfg.for_camera(cam)
    pol = cfg.policy.model_copy(update={"pause_ratio": float(cfg.policy.pause_ratio)})
    c = cfg.topview.center_mm
    part = window_part(center=(float(c[0]), float(c[1])))
    tot = {"layers": 0, "layer_alarms": 0, "policy_alarms": 0, "pauses": 0, "max_a": 0.0, "sum_a": 0.0}
    t0 = time.perf_counter()
    for s in seeds:
        got = _clean_print(part, cfg, cam, pol, s, None, lambda: None)
        mean_a = sum(got["a"]) / max(len(got["a"]), 1)
        print(f"seed {s}: layers {got['layers']} alarms {got['layer_alarms']} policy {got['policy_alarms']} "
              f"pauses {got['pauses']} max_a {got['max_a']:.4f} mean_a {mean_a:.5f}", flush=True)
        for k in ("layers", "layer_alarms", "policy_alarms", "pauses"):
            tot[k] += got[k]
        tot["max_a"] = max(tot["max_a"], got["max_a"])
        tot["sum_a"] += sum(got["a"])
    print(f"total: layers {tot['layers']} alarms {tot['layer_alarms']} policy {tot['policy_alarms']} "
          f"pauses {tot['pauses']} max_a {tot['max_a']:.4f} mean_a {tot['sum_a'] / max(tot['layers'], 1):.5f} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
