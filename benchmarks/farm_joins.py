"""What the capacity benchmark's mid-job joins charge its ramp: printers joined as it joins them vs watched from the start.

Run: ``python benchmarks/farm_joins.py [--printers 80] [--window 60] [--pairs 1]`` in a checkout (``PYTHONPATH`` at
its ``src``); ``--printer K --at S``: printer ``K`` alone, joined before layer ``S`` and watched from layer 0, its
records of layers ``S``-32 side by side (decision, area changed beside the print, CPU).

:mod:`farm_capacity` lets each printer join the farm in the middle of its job: its monitor analyses the layer
before its first trigger (not charged), which is meant to build what a farm that watched the job from its start
holds. This runs one window of that benchmark (:func:`farm_capacity.window`, the same printers, phases, layers,
photos and charging) twice in one process, ``--pairs`` times in turn: once with the printers joined that way
(``join``), once with each printer's job replayed from its layer 0 up to its joining layer before the window, not
charged (``start``: the state of a printer watched since its job began; a printer joining at layer 0 starts its
job at its first trigger, its set-up charged, in both). Per mode: CPU per charged frame, verdict latency p50/p99,
and the decisions of the charged frames (a printer watched from its start pauses nothing on this clean print).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

MODES = ("join", "start")


def one_window(scene, mode: str, printers: int, win: float, fast_share: float, seed: int) -> str:
    """One ramp window of ``printers`` joined in ``mode`` (:data:`MODES`): its line of figures."""
    import farm_capacity as fc  # noqa: PLC0415 - sets the thread limits before NumPy/OpenCV load
    import numpy as np  # noqa: PLC0415

    n = scene.toolpath.n_layers
    runner = fc.Runner(scene)
    rng = np.random.default_rng(seed)
    ps: list = []
    t0 = time.perf_counter()
    try:
        for _ in range(printers):  # the phases and layers the capacity benchmark's ramp draws
            period = 10.0 if rng.random() < fast_share else 60.0
            p = fc.Printer(len(ps), period, rng.random() * period, int(rng.integers(n)))
            ps.append(p)
            if mode == "join":
                runner.join(p)
                continue
            runner.attach(p)
            for i in range(p.start):  # the job so far, as a farm watching it since its start saw it (not charged)
                runner.frame(p, i, scene.jpeg(p.index, i))
            p.joined = True
            if p.start == 0:  # its job starts at its first trigger: built there, charged, as the benchmark's
                runner.close([p], pool=False)
        joins_s = time.perf_counter() - t0
        runner.charged_s = 0.0
        decisions: Counter[str] = Counter()
        frame = runner.frame

        def counted(p, layer: int, jpeg: bytes) -> tuple[float, bool]:
            out = frame(p, layer, jpeg)
            if out[1]:  # a charged frame: its record's decision
                decisions[p.mon.report.results[-1].decision] += 1
            return out

        runner.frame = counted  # type: ignore[method-assign]
        lat, _ = fc.window(ps, runner, 0.0, win)
    finally:
        runner.close(ps)
    return (f"{mode:5s} printers={printers} frames={len(lat)} cost={runner.charged_s / max(len(lat), 1) * 1e3:.1f} "
            f"ms/frame p50={np.percentile(lat, 50):.3f}s p99={np.percentile(lat, 99):.3f}s "
            f"decisions={dict(sorted(decisions.items()))} (set-up {joins_s:.0f}s) load={os.getloadavg()[0]:.1f}")


def one_printer(scene, k: int, at: int) -> list[str]:
    """Printer ``k``'s layers ``at``.. joined before ``at`` (as the ramp joins) and watched from layer 0: a line each."""
    import farm_capacity as fc  # noqa: PLC0415

    n = scene.toolpath.n_layers
    runs: dict[str, dict[int, tuple[str, float, float]]] = {}
    for mode, first in (("start", 0), ("join", at - 1)):
        runner, p, pool = fc.inline_printer(scene, k)
        out = runs[mode] = {}
        for i in range(first, n):
            t = time.process_time()
            runner.frame(p, i, scene.jpeg(k, i))
            assert p.mon is not None
            r = p.mon.report.results[-1]
            out[i] = (r.decision, float(r.outside_anomalous_mm2 or 0.0), (time.process_time() - t) * 1e3)
        runner.close([p])
        pool.close()
    return [f"layer {i:2d}: from layer 0 {runs['start'][i][0]:6s} beside {runs['start'][i][1]:6.1f} mm2 "
            f"{runs['start'][i][2]:5.0f} ms | joined {runs['join'][i][0]:6s} beside {runs['join'][i][1]:6.1f} mm2 "
            f"{runs['join'][i][2]:5.0f} ms" for i in range(at, n)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--printers", type=int, default=80)
    ap.add_argument("--window", type=float, default=60.0, help="farm seconds of the window (default 60)")
    ap.add_argument("--pairs", type=int, default=1, help="join/start windows in turn (default 1)")
    ap.add_argument("--fast-share", type=float, default=0.1, help="share of printers at one layer per 10 s")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--printer", type=int, default=None, metavar="K", help="printer K alone (with --at)")
    ap.add_argument("--at", type=int, default=None, metavar="S", help="the layer printer K joins before (1..32)")
    a = ap.parse_args(argv)
    if (a.printers < 1 or a.window <= 0 or a.pairs < 1 or not 0.0 <= a.fast_share <= 1.0
            or (a.printer is None) != (a.at is None) or (a.at is not None and not 1 <= a.at <= 32)):
        ap.error("--printers >= 1, --window > 0, --pairs >= 1, --fast-share in [0, 1]; --printer with --at in 1..32")
    import farm_capacity as fc  # noqa: PLC0415

    scene = fc.Scene(layers=33)
    if a.printer is not None:
        print(*one_printer(scene, a.printer, a.at), sep="\n")
        return 0
    warm = fc.Runner(scene)
    first = fc.Printer(-1, 60.0, 0.0)
    warm.attach(first)
    warm.frame(first, 0, scene.jpeg(0, 0))  # compile and import what the first frame needs, untimed
    warm.close([first])
    for _ in range(a.pairs):
        for mode in MODES:
            print(one_window(scene, mode, a.printers, a.window, a.fast_share, a.seed), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
