"""Capacity of one farm service: printers per core, memory per printer, verdict latency p99.

Run: ``python benchmarks/farm_capacity.py [--quick] [--dask N] [--dask-speedup N]`` (``make bench`` runs ``--quick``).

What is measured
----------------
* **The work is real.** Every simulated layer of every printer runs the farm's
  per-layer task (:func:`layerwatch.farm.remote.analyse_on`: reference rendering
  in the printer's own incremental pipeline, warp of a 1920x1080 photo, HOG
  analysis, overlay thumbnail) on its own :class:`LayerPipeline`. Every
  printer has its own distinct photos (the simulated print of the example
  part at 1080p, shifted by a per-printer offset of a few pixels and scaled by a
  per-printer gain: the camera's part, not timed).
* **The clock is virtual.** Printers print one layer per minute (a share,
  ``--fast-share``, one per 10 s), their jobs started at random times, layer 0
  first. Triggers are placed on a virtual timeline; ``W`` virtual workers
  (``W = 1``: one core; ``--dask N``: ``N``) take frames first come first
  served, one frame per printer at a time, and each frame occupies its worker
  for the *measured* wall time of its work. Verdict latency = virtual finish -
  trigger. So a minute of farm time costs only the compute it needs, and the
  queueing is what a saturated pool would see.
* **Ramp.** ``N`` grows (x1.25; ``--quick`` x1.5 with 20 s windows) from 70 % of the estimate
  made with one warm frame's cost until the latency p99 of a window exceeds 2 s; ``printers_per_core`` is the
  largest ``N`` that kept p99 <= 2 s, divided by the workers.
* **Memory.** Resident set growth of this process over the ``N`` printers'
  pipelines, divided by ``N`` (many printers of the last window have not analysed a
  layer yet, so this reads low); and the **long run**: a few printers with what a farm
  station holds for a job (:class:`FarmMonitor`, its pool pipeline), fed every layer
  of the part, read after 2 layers and after the last. The final figure is the larger.
* **Baseline** (same run): the single-printer monitor
  (:class:`~layerwatch.monitor.service.Monitor` with a virtual printer and the
  same photos): its time per layer, and the resident set of a process running
  it (what one ``layerwatch monitor`` process per printer costs).

``--dask N``: the per-layer task runs through the farm's :class:`WorkerPool` on a
:class:`distributed.LocalCluster` of ``N`` worker processes (jobs pinned, each
layer's photo sent to its worker); the run then compares the pool on ``N``
workers with one on the same frames (:func:`dask_speedup`) and prints the
throughput ratio. ``--dask-speedup N`` runs only that comparison (about a minute):
its last line reads ``dask_speedup=<r> workers=<N> records_identical=<bool>``.

The last line reads ``printers_per_core=<n> mb_per_printer=<m> p99_s=<s>``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import ctypes  # noqa: E402
import heapq  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from concurrent.futures import ThreadPoolExecutor  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import numpy as np  # noqa: E402

from layerwatch.examples import PART_CONFIG, PART_GCODE  # noqa: E402
from layerwatch.farm.monitor import FarmMonitor, PoolPipeline  # noqa: E402
from layerwatch.farm.pool import WorkerPool  # noqa: E402
from layerwatch.farm.remote import JobContext, analyse_on  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.monitor.cameras import SimCamera  # noqa: E402
from layerwatch.monitor.printers.base import SnapshotTrigger  # noqa: E402
from layerwatch.monitor.printers.virtual import VirtualPrinter  # noqa: E402
from layerwatch.monitor.service import Monitor  # noqa: E402
from layerwatch.pipeline.config import resolve_config  # noqa: E402
from layerwatch.pipeline.policy import PausePolicy  # noqa: E402
from layerwatch.pipeline.step import LayerPipeline  # noqa: E402
from layerwatch.simulate import PrintSimulator, default_camera  # noqa: E402

P99_LIMIT_S = 2.0
PHOTO = (1920, 1080)


def rss_mb() -> float:
    """Resident set of this process, MB, after glibc returned its free heap pages (``malloc_trim``).

    The photos of a window are freed when it ends; without the trim the allocator's free pages
    (reused by the next window anyway) would count as memory held by the printers.
    """
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:  # not glibc: plain RSS
        pass
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


class Scene:
    """The example part, its settings, a 1080p camera and the simulated photos of its layers."""

    def __init__(self, layers: int) -> None:
        self.cfg = resolve_config(PART_CONFIG).config
        self.toolpath = read_toolpath(PART_GCODE)
        tv = self.cfg.topview.topview()
        self.camera = default_camera(tv, image_size=PHOTO)
        self.layers = min(layers, self.toolpath.n_layers)
        sim = PrintSimulator(self.toolpath, self.camera, tv, [], seed=1)
        self.frames = [sim.frame(i).photo for i in range(self.layers)]

    def photo(self, printer: int, layer: int) -> np.ndarray:
        """Printer ``printer``'s own photo of ``layer``: shifted by a few px, its own gain."""
        rng = np.random.default_rng(printer)
        dy, dx = rng.integers(-3, 4, 2)
        gain = 0.9 + 0.2 * rng.random()
        img = np.roll(self.frames[layer % self.layers], (int(dy), int(dx)), axis=(0, 1))
        return np.clip(img * gain, 0, 255).astype(np.uint8)

    def pipeline(self) -> LayerPipeline:
        return JobContext("bench", self.toolpath, self.camera, self.cfg).pipeline()  # as a farm printer's


@dataclass
class Printer:
    index: int
    period_s: float
    next_t: float
    pipe: LayerPipeline | None = None
    remote: PoolPipeline | None = None
    layer: int = 0
    free_t: float = 0.0  # virtual time its previous frame's verdict came
    latencies: list[float] = field(default_factory=list)


class Runner:
    """Runs frames: here (one core), or through the farm's :class:`WorkerPool` on a Dask cluster (``N`` in flight)."""

    def __init__(self, scene: Scene, pool: WorkerPool | None = None, workers: int = 1) -> None:
        self.scene, self.pool, self.workers = scene, pool, workers
        self.client = pool.client if pool is not None else None

    def attach(self, p: Printer) -> None:
        if self.pool is None:
            p.pipe = self.scene.pipeline()
        else:  # as a farm station builds it: the job scattered once, pinned to the least loaded worker
            ctx = JobContext(f"bench/{p.index}", self.scene.toolpath, self.scene.camera, self.scene.cfg)
            p.remote = PoolPipeline(self.pool, ctx.pipeline(), ctx)

    def run(self, batch: list[tuple[Printer, int, np.ndarray]]) -> list[float]:
        """Wall seconds of each frame's work (the batch runs ``workers`` at a time)."""
        if self.pool is None:
            out = []
            for p, layer, photo in batch:
                t = time.perf_counter()
                analyse_on(p.pipe, photo, layer)
                out.append(time.perf_counter() - t)
            return out

        def one(item):
            p, layer, photo = item
            t = time.perf_counter()
            p.remote.process(photo, layer)
            return time.perf_counter() - t

        with ThreadPoolExecutor(self.workers) as ex:
            return list(ex.map(one, batch))


def window(printers: list[Printer], runner: Runner, t0: float, t1: float) -> list[float]:
    """Simulate [t0, t1) of farm time; returns the verdict latencies of its triggers, s."""
    events = []
    for p in printers:
        while p.next_t < t1:
            events.append((p.next_t, p.index, p.layer))
            p.layer += 1
            p.next_t += p.period_s
    events.sort()
    servers = [t0] * runner.workers
    heapq.heapify(servers)
    lat: list[float] = []
    by_index = {p.index: p for p in printers}
    for i in range(0, len(events), runner.workers):  # frames in trigger order, `workers` at a time
        chunk = events[i:i + runner.workers]
        batch = [(by_index[k], layer, runner.scene.photo(k, layer)) for _, k, layer in chunk]
        costs = runner.run(batch)
        for (t, k, _), cost in zip(chunk, costs, strict=True):
            p = by_index[k]
            start = max(t, heapq.heappop(servers), p.free_t)
            p.free_t = start + cost
            heapq.heappush(servers, p.free_t)
            lat.append(p.free_t - t)
    return lat


def baseline(scene: Scene, layers: int) -> tuple[float, float]:
    """The single-printer monitor on the same photos: (s per layer, process RSS MB)."""
    gcode = "".join(f"G1 Z{0.2 * (i + 1):.2f}\n@layerwatch snapshot layer={i} z={0.2 * (i + 1):.2f}\n"
                    for i in range(layers)).encode()
    printer = VirtualPrinter(gcode, name="bench.gcode")
    cam = SimCamera(lambda i: scene.photo(0, i))
    mon = Monitor(printer, cam, scene.pipeline(), PausePolicy(scene.cfg.policy), wait_for_verdict=True)
    t = time.perf_counter()
    rep = mon.run(poll_s=0.0)
    per = (time.perf_counter() - t) / max(1, len(rep.results))
    return per, rss_mb()


def ramp(runner: Runner, rng: np.random.Generator, n: int, step: float, win: float, fast_share: float,
         t_start: float) -> tuple[int, float, float]:
    """Add printers (x ``step`` per window of ``win`` farm seconds) until the latency p99 passes 2 s.

    Returns
    -------
    (int, float, float)
        The most printers that kept p99 <= 2 s, their MB per printer and p99, s.
    """
    client = runner.client
    printers: list[Printer] = []
    best = (0, 0.0, float("nan"))
    t = 0.0
    mem0 = rss_mb()
    work0 = worker_mb(client) if client is not None else 0.0
    while True:
        while len(printers) < n:  # new jobs start at random times in the coming window, layer 0 first
            period = 10.0 if rng.random() < fast_share else 60.0
            p = Printer(len(printers), period, t + rng.random() * period)  # uniform phase: steady state
            runner.attach(p)
            printers.append(p)
        for p in printers:
            p.free_t = max(p.free_t, t)
        lat = window(printers, runner, t, t + win)
        t += win
        p99 = float(np.percentile(lat, 99)) if lat else float("nan")
        mem = (rss_mb() - mem0) / len(printers) if client is None else worker_mb(client, work0) / len(printers)
        print(f"N={len(printers):5d} frames={len(lat):5d} p50={np.percentile(lat, 50):.3f}s p99={p99:.3f}s "
              f"MB/printer={mem:.2f} elapsed={time.perf_counter() - t_start:.0f}s", flush=True)
        if p99 > P99_LIMIT_S and best[0] == 0 and n > 10:  # the first step was already too many: start lower
            printers.clear()
            n = max(10, n // 2)
            continue
        if p99 > P99_LIMIT_S:
            return best
        best = (len(printers), mem, p99)
        n = int(n * step) + 1


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="short windows (finishes in under 3 minutes)")
    ap.add_argument("--dask", type=int, default=0, metavar="N", help="run on a LocalCluster of N worker processes")
    ap.add_argument("--dask-speedup", type=int, default=0, metavar="N",
                    help="only compare the farm pool on N Dask worker processes with one (throughput ratio)")
    ap.add_argument("--fast-share", type=float, default=0.1, help="share of printers at one layer per 10 s")
    ap.add_argument("--window", type=float, default=None, help="farm seconds per ramp step (default 20 quick, 120)")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    if not (0.0 <= a.fast_share <= 1.0) or a.dask < 0 or not (a.dask_speedup == 0 or 2 <= a.dask_speedup <= 64):
        ap.error("--fast-share must be in [0, 1], --dask >= 0 and --dask-speedup in [2, 64]")
    t_start = time.perf_counter()
    if a.dask_speedup:
        scene = Scene(layers=8)
        ratio, same = dask_speedup(scene, a.dask_speedup)
        line = f"dask_speedup={ratio:.2f} workers={a.dask_speedup} records_identical={same}"
        print(line)
        return line
    win = a.window or (20.0 if a.quick else 120.0)
    step = 1.5 if a.quick else 1.25
    scene = Scene(layers=12 if a.quick else 33)
    warm = scene.pipeline()
    analyse_on(warm, scene.photo(0, 0), 0)  # compile and import what the first frame needs, untimed
    t = time.perf_counter()
    for i in range(1, 7):
        analyse_on(warm, scene.photo(0, i), i)
    per_frame = (time.perf_counter() - t) / 6
    del warm
    per_layer, rss_base = baseline(scene, 8)
    rate = (1 - a.fast_share) / 60.0 + a.fast_share / 10.0  # layers per printer per s
    print(f"farm per-layer task {per_frame * 1e3:.0f} ms/frame (warm); baseline: single-printer monitor {per_layer * 1e3:.0f} ms/layer, process RSS {rss_base:.0f} MB "
          f"(one monitor process per printer); layer rate {rate * 60:.2f}/min per printer", flush=True)
    soak_mb = soak(scene, 6 if a.quick else 12) if not a.dask else 0.0
    pool = None
    workers = 1
    if a.dask:
        pool = WorkerPool(a.dask, scheduler="local")
        workers = a.dask
    runner = Runner(scene, pool, workers)
    n0 = max(10, int(0.7 * workers / (rate * per_frame)))  # ramp from 70 % of the estimate of one frame's cost
    try:
        best = ramp(runner, np.random.default_rng(a.seed), n0, step, win, a.fast_share, t_start)
    finally:
        if pool is not None:
            pool.close()
    n_ok, mb, p99 = best
    if a.dask:
        ratio, same = dask_speedup(scene, a.dask)
        print(f"dask: {a.dask} worker processes, throughput {ratio:.2f}x one worker process on the same frames, "
              f"records identical: {same}")
    ppc = n_ok / workers
    mb = max(mb, soak_mb)  # the larger of the ramp's and the long run's figure
    print(f"ratio vs baseline: {ppc:.0f} printers per core in one farm process vs one printer per monitor "
          f"process ({rss_base:.0f} MB each); memory per printer {rss_base / max(mb, 1e-9):.0f}x less; "
          f"CPU per layer: monitor {per_layer * 1e3:.0f} ms vs farm task {per_frame * 1e3:.0f} ms")
    line = f"printers_per_core={ppc:.0f} mb_per_printer={mb:.1f} p99_s={p99:.3f}"
    print(line)
    return line


def worker_mb(client, since: float = 0.0) -> float:
    """Resident set of all the cluster's worker processes, MB, minus ``since``."""
    sizes = client.run(lambda: rss_mb())
    return sum(sizes.values()) - since


def soak(scene: Scene, n: int) -> float:
    """Memory per printer of a farm's per-printer state over a long run (every layer of the scene's part).

    Two groups of ``n`` printers, each printer with what a farm station holds for a job
    (:class:`FarmMonitor`, its :class:`PoolPipeline` and pipeline on a local :class:`WorkerPool`),
    each group fed every layer in turn. The figure is the *second* group's resident-set growth over
    ``n``: what one more printer costs. The first group also pays the process's one-time costs
    (allocator arenas of the new threads, OpenCV and NumPy buffers made on first use), which a
    farm of hundreds spreads over all its printers; divided over a handful of printers they
    would read as several MB each. The resident set can also read *low*: the second group may
    reuse pages the allocator kept from earlier work. So the second group's allocations are also
    traced (:mod:`tracemalloc`: every NumPy and Python block made since the group started and
    still held), and the larger of the two growths is the figure. All figures are printed.

    Returns
    -------
    float
        MB per printer of the second group after its last layer: the larger of its resident-set
        growth and its traced allocations still held.
    """
    gcode = b"G1 Z0.2\n"
    pool = WorkerPool(1)
    mons: list[FarmMonitor] = []
    try:
        mem = [rss_mb()]
        seen = {}
        for group in range(2):
            if group == 1:
                tracemalloc.start()
            new = []
            for k in range(group * n, (group + 1) * n):
                ctx = JobContext(f"soak/{k}", scene.toolpath, scene.camera, scene.cfg)
                new.append(FarmMonitor(VirtualPrinter(gcode), SimCamera(lambda i, k=k: scene.photo(k, i)),
                                       PoolPipeline(pool, ctx.pipeline()), PausePolicy(scene.cfg.policy),
                                       wait_for_verdict=True, faults=scene.cfg.faults,
                                       frame_quality=scene.cfg.frame_quality))  # as a farm station builds it
            mons += new
            for layer in range(scene.layers):
                for mon in new:
                    mon.handle_trigger(SnapshotTrigger(layer, 0.2 * (layer + 1), "soak", time.monotonic()))
                if group == 1 and layer + 1 == 2:
                    seen[2] = (rss_mb() - mem[-1]) / n
            mem.append(rss_mb())
        traced = tracemalloc.get_traced_memory()[0] / 2**20 / n
        tracemalloc.stop()
        seen[scene.layers] = (mem[2] - mem[1]) / n
        print(f"long run: {n} more printers' farm state (monitor, pipeline), MB/printer after "
              + ", ".join(f"{k} layers {v:.2f}" for k, v in seen.items())
              + f"; traced allocations held after {scene.layers} layers {traced:.2f}"
              + f" (the first {n}, with the process's one-time costs: {(mem[1] - mem[0]) / n:.2f})", flush=True)
        return max(seen[scene.layers], traced)
    finally:
        for mon in mons:
            mon.close()
        pool.close()


def _record(res) -> dict:
    """A layer record without its timings (what must match between runs)."""
    d = res.to_dict()
    d.pop("timings_ms", None)
    if d.get("scene"):
        d["scene"].pop("ms", None)
    return d


def _cpu(pids: list[int]) -> np.ndarray:
    """CPU seconds used so far by this process and by the processes ``pids`` together."""
    def one(pid: int) -> float:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    return np.array([time.process_time(), sum(one(p) for p in pids)])


def dask_speedup(scene: Scene, n: int) -> tuple[float, bool]:
    """Throughput of the farm pool on ``n`` Dask worker processes over one, and whether the records match.

    Both clusters run in this process at once; ``4 n`` printers' jobs go through
    :class:`WorkerPool` as a farm sends them (one lane thread per printer, jobs pinned). Each
    round is one layer of every printer, on one pool then the other (the order alternating, so
    both see the same load); the photos are made before a round (the camera's part, not timed)
    and the first layer, which builds each worker's pipelines, is not timed. The records of
    both pools are compared with each other and, for the first printer, with a local pipeline.

    Returns
    -------
    (float, bool)
        Wall time on one worker / on ``n`` workers; every record identical.
    """
    printers = 4 * n
    pools, pipes = [], []
    try:
        for w in (1, n):
            pool = WorkerPool(w, scheduler="local")
            pools.append(pool)
            pipes.append([PoolPipeline(pool, ctx.pipeline(), ctx) for ctx in (
                JobContext(f"speed/{w}/{k}", scene.toolpath, scene.camera, scene.cfg) for k in range(printers))])
        elapsed, cpu = [0.0, 0.0], np.zeros((2, 2))  # per pool: wall s; (service, workers) CPU s
        pids = [list(pool.client.run(os.getpid).values()) for pool in pools]
        records: list[list[dict]] = [[], []]
        with ThreadPoolExecutor(printers) as lanes:
            for layer in range(scene.layers):
                photos = [scene.photo(k, layer) for k in range(printers)]
                for j in ((0, 1) if layer % 2 else (1, 0)):
                    t, c = time.perf_counter(), _cpu(pids[j])
                    out = list(lanes.map(PoolPipeline.process, pipes[j], photos, [layer] * printers))
                    if layer > 0:
                        elapsed[j] += time.perf_counter() - t
                        cpu[j] += _cpu(pids[j]) - c
                    records[j] += [_record(r) for r in out]
        local = scene.pipeline()
        mine = [_record(analyse_on(local, scene.photo(0, i), i).result) for i in range(scene.layers)]
        same = records[0] == records[1] and mine == records[1][::printers]
        loads = [sorted(p.jobs_per_worker.values()) for p in pools]
        frames = printers * (scene.layers - 1)
        print(f"dask: {printers} printers x {scene.layers - 1} timed layers; one worker {elapsed[0]:.2f} s, {n} workers "
              f"{elapsed[1]:.2f} s (jobs per worker {loads[1]}); {os.cpu_count()} cores, load average "
              f"{os.getloadavg()[0]:.1f}", flush=True)
        print("dask: CPU per frame (service process with the scheduler + worker processes): "
              + "; ".join(f"{w} worker(s) {cpu[j, 0] / frames * 1e3:.0f} + {cpu[j, 1] / frames * 1e3:.0f} ms"
                          for j, w in enumerate((1, n))), flush=True)
        return elapsed[0] / elapsed[1], same
    finally:
        for row in pipes:
            for pp in row:
                pp.close()
        for pool in pools:
            pool.close()


if __name__ == "__main__":
    main()
