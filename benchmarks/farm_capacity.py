"""Capacity of one farm service: printers per core, memory per printer, verdict latency p99.

Run: ``python benchmarks/farm_capacity.py [--quick] [--same-file S] [--bisect K] [--dask N] [--dask-speedup N]`` (``make bench`` runs ``--quick``).

What is measured
----------------
* **The work is real.** Every simulated layer of every printer goes through what a
  farm runs per frame, in the process that runs it: the printer's
  :class:`FarmMonitor` takes the photo as a camera delivers it (a 1080p JPEG
  snapshot, decoded), runs the camera-fault gate (exposure, noise, JPEG blocking,
  repeated frame, bed markers), hands the per-layer task
  (:func:`layerwatch.farm.remote.analyse_on`: reference rendering in the
  printer's own incremental pipeline, warp, HOG analysis, scene channel, failure
  typing, job checks, overlay thumbnail) to the farm's :class:`WorkerPool`, runs
  the lag check where a result would count toward a pause, and the policy. Every
  printer has its own distinct photos (the simulated print of the example part at
  1080p, shifted by a per-printer offset of a few pixels, scaled by a per-printer
  gain and JPEG-encoded: the camera's part, not timed).
* **Steady state.** A printer joins the farm in the middle of a job (its phase and
  its layer uniform). As it joins, its monitor analyses the layer before its first
  trigger, which builds the reference stack and the one-time maps a farm that watched the
  job from its start holds; that frame is not charged, every trigger after it is. Its scene
  channel takes that mid-job photo as its baseline, with the printed body of the layers before
  it from the plan (until c4b8200 it knew only the layers after the join, and most printers that
  joined past the first layers reported changes beside the print, ~5-8 ms a frame more over a
  window: ``farm_joins.py``; docs/farm.md, session 22). A printer that finished the part starts it again as a
  new job: building its monitor and pipeline is charged with that job's first frame, the
  printer's view maps kept from its last job as a farm station keeps them
  (:mod:`layerwatch.pipeline.job_geometry`; job starts thus come at a farm's steady-state
  rate; the example part has 33 layers, so set-up weighs more here than on real prints of
  hundreds; the G-code is parsed once for all, where a station parses each job's, ~10 ms). Charging the
  joins instead would make every ramp step a wave of job starts (a third of the
  frames of a 20 s window), which no farm sees.
* **The clock is virtual.** Printers print one layer per minute (a share,
  ``--fast-share``, one per 10 s). Triggers are placed on a virtual timeline; ``W`` virtual workers
  (``W = 1``: one core; ``--dask N``: ``N``) take frames first come first
  served, one frame per printer at a time, and each frame occupies its worker
  for the *measured* time of its work: with local threads the CPU time this process
  spent on it (all its threads; the machine may be shared, and a printer per core is
  about a core's worth of compute: wall time would count the neighbours' load too, so
  the windows print both), on Dask its wall time. Verdict latency = virtual finish -
  trigger. So a minute of farm time costs only the compute it needs, and the
  queueing is what a saturated pool would see.
* **Ramp.** ``N`` grows (x1.25; ``--quick`` x1.3 with 20 s windows) from 70 % of the estimate
  made with one warm frame's cost until the latency p99 of a window exceeds 2 s; then ``--bisect K``
  windows (3; ``--quick`` 2) halve the interval between the last step that passed and the first that
  failed (the printers past a window's count are parked: their jobs held, and their memory counted). A
  window stops as soon as enough of its frames are over 2 s for its p99 to be over 2 s whatever the
  rest would be (its p50/p99 are then those of the frames run); ``--quick`` starts no window predicted to
  end after 170 s (``--budget-s``: a ramp or bisection cut short leaves the last step that passed, a lower
  bound);
  ``printers_per_core`` is the largest ``N`` that kept p99 <= 2 s, divided by the workers.
* **Shared files.** By default every printer prints a file of its own (nothing is shared between
  printers: each renders its own references). ``--same-file S``: a share ``S`` of the printers print
  one file with one camera model, and the farm renders each of its layers once for all of them
  (:mod:`layerwatch.pipeline.shared_references`; their photos stay distinct); the last line then ends
  with ``same_file=S``.
* **Memory.** Resident set growth of this process over the ``N`` printers'
  monitors and pipelines, divided by ``N`` (many printers of the last window have not
  analysed a layer yet, so this reads low); and the **long run** (:func:`soak`): groups of
  printers with what a farm station holds for a job (:class:`FarmMonitor`, its pool pipeline)
  added until 4, 8 and 16 (``--quick``; else 4, 16 and 64) hold a job, each group fed the first
  layers of the part; its figure is the *slope* of the resident set over the printer count, with
  the traced allocations per printer beside it (the larger of the two; the slope of glibc's bytes
  in use, ``mallinfo2``, is printed too). The final figure is the larger of the ramp's and the
  long run's.
* **Baseline** (same run): the single-printer monitor
  (:class:`~layerwatch.monitor.service.Monitor` with a virtual printer, the job's
  camera-fault gate and the same JPEG photos): its time per layer, and the resident set of a process running
  it (what one ``layerwatch monitor`` process per printer costs).

``--dask N``: the per-layer task runs through the farm's :class:`WorkerPool` on a
:class:`distributed.LocalCluster` of ``N`` worker processes (jobs pinned, each
layer's JPEG snapshot sent to its worker, which decodes, gates and analyses it); the
run then compares a farm on ``N`` workers with one (:func:`dask_speedup`) and prints the
throughput ratio. ``--dask-speedup N`` runs only that comparison (1-2 minutes):
its last line reads ``dask_speedup=<r> workers=<N> records_identical=<bool>``. It runs
the farm's whole per-frame path (a :class:`FarmMonitor` per printer on JPEG snapshots)
with the printers' jobs staggered and **no rounds**: each printer sends its next frame
when its verdict came, and the throughput is read while every printer is still sending
(:func:`dask_speedup` says why: an earlier version's rounds were a barrier the farm
does not have, and it timed only the pool's task, not the decoding, gate and lag check).

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

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)  # one core per worker: OpenCV's own thread pool would spread a frame over the machine's cores

from layerwatch.examples import PART_CONFIG, PART_GCODE  # noqa: E402
from layerwatch.farm.monitor import FarmMonitor, PoolPipeline  # noqa: E402
from layerwatch.farm.pool import WorkerPool  # noqa: E402
from layerwatch.farm.remote import JobContext  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.monitor.cameras import Camera, SimCamera  # noqa: E402
from layerwatch.monitor.printers.base import SnapshotTrigger  # noqa: E402
from layerwatch.monitor.printers.virtual import VirtualPrinter  # noqa: E402
from layerwatch.monitor.service import Monitor  # noqa: E402
from layerwatch.pipeline.config import resolve_config  # noqa: E402
from layerwatch.pipeline.policy import PausePolicy  # noqa: E402
from layerwatch.pipeline.step import LayerPipeline  # noqa: E402
from layerwatch.simulate import PrintSimulator, default_camera  # noqa: E402

P99_LIMIT_S = 2.0
PHOTO = (1920, 1080)
#: JPEG quality of the simulated snapshots (a webcam's usual 85-95)
JPEG_QUALITY = 90


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


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]


def malloc_in_use_mb() -> float:
    """Bytes glibc's ``malloc`` has handed out and not had back (``mallinfo2``: heap chunks in use + mmapped
    blocks), MB: every native allocation (NumPy, OpenCV), without the free pages the allocator keeps; NaN
    where there is no ``mallinfo2`` (not glibc, or older than 2.33)."""
    try:
        f = ctypes.CDLL("libc.so.6").mallinfo2
    except (OSError, AttributeError):
        return float("nan")
    f.restype = _MallInfo2
    m = f()
    return (m.uordblks + m.hblkhd) / 2**20


class Scene:
    """The example part, its settings, a 1080p camera and the simulated photos of its layers."""

    def __init__(self, layers: int, march: str | None = None) -> None:
        self.cfg = resolve_config(PART_CONFIG).config
        if march is not None:  # ``--march``: how the volume reference is ray-marched (``render.march``)
            self.cfg = self.cfg.model_copy(update={"render": self.cfg.render.model_copy(update={"march": march})})
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
        return cv2.convertScaleAbs(img, alpha=gain)  # gain x grey, rounded and saturated to 0..255 (fast)

    def jpeg(self, printer: int, layer: int) -> bytes:
        """:meth:`photo` as the camera's JPEG snapshot."""
        ok, data = cv2.imencode(".jpg", self.photo(printer, layer), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        assert ok
        return data.tobytes()

    def pipeline(self) -> LayerPipeline:
        return JobContext("bench", self.toolpath, self.camera, self.cfg).pipeline()  # as a farm printer's


class SnapshotBytes(Camera):
    """A snapshot camera whose JPEG bytes were fetched before :meth:`grab`: decoding and checking them is the farm's work."""

    where = "benchmark camera"

    def __init__(self) -> None:
        super().__init__(retries=0, stale_check=True)  # as a snapshot URL camera
        self.data = b""

    def _fetch(self) -> bytes:
        return self.data  # grab(): decoded here; on the farm's Dask workers sent as they are (grab_encoded)


@dataclass
class Printer:
    index: int
    period_s: float
    next_t: float
    start: int = 0  # layer of its job at which the printer joined the farm
    same_file: bool = False  # prints the file the other `same_file` printers print (their references are shared)
    mon: FarmMonitor | None = None
    cam: SnapshotBytes | None = None
    job: int = 0  # jobs started (the part printed again after its last layer)
    layer: int = 0  # layers triggered since it joined
    joined: bool = False  # its first frame in the farm was analysed (the state it holds is built)
    setup_s: float = 0.0  # wall time of building the current job's monitor, added to its first frame
    free_t: float = 0.0  # virtual time its previous frame's verdict came
    latencies: list[float] = field(default_factory=list)


class Runner:
    """Runs frames through each printer's :class:`FarmMonitor` on the farm's :class:`WorkerPool`.

    Local threads (one core: one frame at a time), or a Dask cluster (``workers`` frames in flight).
    """

    def __init__(self, scene: Scene, pool: WorkerPool | None = None, workers: int = 1) -> None:
        self.scene, self.workers = scene, workers
        #: the clock a frame's cost is read on: this process's CPU time with local threads, else wall time
        self.clock = time.process_time if pool is None else time.perf_counter
        self.wall_s = self.charged_s = 0.0  # totals over the charged frames (wall, and on ``clock``)
        self.own_pool = pool is None
        self.pool = pool if pool is not None else WorkerPool(1)
        self.client = pool.client if pool is not None else None

    def attach(self, p: Printer) -> None:
        """Start a job on ``p``: its monitor and pipeline as a farm station builds them (timed into ``setup_s``)."""
        t = self.clock()
        if p.mon is not None:
            p.mon.close()
            p.mon.pipeline.close()
        ctx = JobContext(f"bench/{p.index}/{p.job}", self.scene.toolpath, self.scene.camera, self.scene.cfg,
                         share_references=p.same_file, printer=f"bench/{p.index}")  # as a farm station's job
        cfg = self.scene.cfg
        p.cam = SnapshotBytes()
        p.mon = FarmMonitor(VirtualPrinter(b"G1 Z0.2\n"), p.cam, PoolPipeline(self.pool, ctx.pipeline(), ctx),
                            PausePolicy(cfg.policy), wait_for_verdict=True, faults=cfg.faults,
                            frame_quality=cfg.frame_quality)
        p.job += 1
        p.setup_s = self.clock() - t

    def frame(self, p: Printer, layer: int, jpeg: bytes) -> tuple[float, bool]:
        """Wall seconds of the farm's work on ``p``'s frame of its job's layer ``layer``, and whether they count.

        A job that starts (the printer finished the part and starts it again) is built here and
        its set-up is part of its first frame. The first frame of a printer that just joined the
        farm in the middle of its job does not count: it builds the state (scene baseline,
        reference stack, one-time maps) that a farm watching the job since its start holds. Job
        starts are charged where they happen, at a farm's steady-state rate (the joining
        printers' layers are uniform over the job).
        """
        n = self.scene.toolpath.n_layers
        if p.mon is None or (layer == 0 and p.joined):  # (a new job: the printer starts the part again)
            self.attach(p)
        assert p.mon is not None and p.cam is not None
        p.cam.data = jpeg
        t, wall = self.clock(), time.perf_counter()
        p.mon.handle_trigger(SnapshotTrigger(layer, float(self.scene.toolpath.layers[layer % n].z), "bench",
                                             time.monotonic()))
        cost, p.setup_s = self.clock() - t + p.setup_s, 0.0
        counts, p.joined = p.joined, True
        if counts:
            self.wall_s += time.perf_counter() - wall
            self.charged_s += cost
        return cost, counts

    def join(self, p: Printer) -> None:
        """``p`` joins the farm before its layer ``p.start``: its job's monitor analyses the layer before (not charged)."""
        n = self.scene.toolpath.n_layers
        self.attach(p)
        layer = (p.start - 1) % n
        self.frame(p, layer, self.scene.jpeg(p.index, layer))

    def run(self, batch: list[tuple[Printer, int, bytes]]) -> list[tuple[float, bool]]:
        """:meth:`frame` of each item (the batch runs ``workers`` at a time)."""
        if self.workers == 1:
            return [self.frame(*item) for item in batch]
        with ThreadPoolExecutor(self.workers) as ex:
            return list(ex.map(lambda item: self.frame(*item), batch))

    def close(self, printers: list[Printer], pool: bool = True) -> None:
        """End the printers' jobs (and the pool this runner made, with ``pool``)."""
        for p in printers:
            if p.mon is not None:
                p.mon.close()
                p.mon.pipeline.close()
                p.mon = None
        if pool and self.own_pool:
            self.pool.close()


def inline_printer(scene: Scene, index: int, same_file: bool = False) -> tuple[Runner, Printer, WorkerPool]:
    """A printer whose pool runs each task inline on the caller's thread (one clock, one order).

    Used by ``farm_steps.py`` (CPU per step) and ``farm_records.py`` (records to compare): the
    job is attached, no frame is run yet. ``same_file``: its references are shared with the other
    ``same_file`` printers (:mod:`layerwatch.pipeline.shared_references`).
    """
    pool = WorkerPool(1)
    pool.run = lambda fn, *a, key=None: fn(*a)  # type: ignore[method-assign]  # inline
    runner = Runner(scene, None)
    runner.pool = pool
    p = Printer(index, 60.0, 0.0, same_file=same_file)
    runner.attach(p)
    return runner, p, pool


def certain_p99_over(limit_count: int) -> int:
    """How many of ``limit_count`` latencies over a limit make their p99 (linear, as :func:`numpy.percentile`) exceed it
    whatever the others are: the order statistic at ``floor(0.99 (n - 1))`` and every one above it."""
    return limit_count - int(np.floor(0.99 * (limit_count - 1)))


def window(printers: list[Printer], runner: Runner, t0: float, t1: float,
           stop_over: float | None = None) -> tuple[list[float], int | None]:
    """Simulate [t0, t1) of farm time: the verdict latencies of its counted frames (s), and the frames it had when it
    stopped early (else None).

    ``stop_over``: the window stops once so many latencies exceed it that the p99 of all the window's
    frames exceeds it whatever the rest would be (:func:`certain_p99_over`): a step that fails is known
    failed without running its backlog. The frames not run are not taken: their printers' next layer
    stays the first one not run, triggered in the next window at the printer's phase (a skipped layer
    would make the next frame's lag check render the layer before it again, from the first layer).
    """
    n = runner.scene.toolpath.n_layers
    events = []
    for p in printers:
        while p.next_t < t1:
            events.append((p.next_t, p.index, (p.start + p.layer) % n))
            p.layer += 1
            p.next_t += p.period_s
    events.sort()
    servers = [t0] * runner.workers
    heapq.heapify(servers)
    lat: list[float] = []
    over, enough = 0, certain_p99_over(len(events))
    by_index = {p.index: p for p in printers}
    for i in range(0, len(events), runner.workers):  # frames in trigger order, `workers` at a time
        chunk = events[i:i + runner.workers]
        batch = [(by_index[k], layer, runner.scene.jpeg(k, layer)) for _, k, layer in chunk]
        costs = runner.run(batch)
        for (t, k, _), (cost, counts) in zip(chunk, costs, strict=True):
            if not counts:  # a printer joining mid-job: its state is built, nothing is charged
                continue
            p = by_index[k]
            start = max(t, heapq.heappop(servers), p.free_t)
            p.free_t = start + cost
            heapq.heappush(servers, p.free_t)
            lat.append(p.free_t - t)
            over += stop_over is not None and lat[-1] > stop_over
        if stop_over is not None and over >= enough and i + runner.workers < len(events):
            for _, k, _ in events[i + runner.workers:]:  # the frames not run are not taken: the layers wait
                by_index[k].layer -= 1
                by_index[k].next_t -= by_index[k].period_s
            return lat, len(events)
    return lat, None


def baseline(scene: Scene, layers: int) -> tuple[float, float]:
    """The single-printer monitor on the same photos: (CPU s per layer, process RSS MB)."""
    gcode = "".join(f"G1 Z{0.2 * (i + 1):.2f}\n@layerwatch snapshot layer={i} z={0.2 * (i + 1):.2f}\n"
                    for i in range(layers)).encode()
    printer = VirtualPrinter(gcode, name="bench.gcode")
    jpegs = [scene.jpeg(0, i) for i in range(layers)]
    cam = SnapshotBytes()
    cam.set_layer = lambda i: setattr(cam, "data", jpegs[i])  # the snapshot of the layer, fetched untimed
    mon = Monitor(printer, cam, scene.pipeline(), PausePolicy(scene.cfg.policy), wait_for_verdict=True,
                  faults=scene.cfg.faults, frame_quality=scene.cfg.frame_quality)  # as `layerwatch monitor` runs it
    t = time.process_time()
    rep = mon.run(poll_s=0.0)
    per = (time.process_time() - t) / max(1, len(rep.results))
    return per, rss_mb()


def ramp(runner: Runner, rng: np.random.Generator, n: int, step: float, win: float, fast_share: float,
         t_start: float, same_file: float = 0.0, bisect: int = 0, budget_s: float | None = None) -> tuple[int, float, float]:
    """Add printers (x ``step`` per window of ``win`` farm seconds) until the latency p99 passes 2 s, then bisect.

    Once a step fails, up to ``bisect`` more windows halve the interval between the most printers
    that passed and the fewest that failed (a printer count between them: the printers past it
    are *parked*, their jobs held and their memory kept, and join again, at their next layer, when a
    later window has more). A window after a failed one starts without the failed one's backlog
    (a farm of that size never built it); after a passed one, the backlog carries over. A share
    ``same_file`` of the printers (drawn per printer) print one file with one camera model and
    share its references (:mod:`layerwatch.pipeline.shared_references`); the rest print files of
    their own and share nothing. With ``budget_s``, no window starts that would end (its joins and its
    frames, predicted from the window before and the joins so far) after the run (since ``t_start``) has
    taken that long: the figure is then the most printers that passed so far (a lower bound).

    Returns
    -------
    (int, float, float)
        The most printers that kept p99 <= 2 s, their MB per printer and p99, s.
    """
    client = runner.client
    printers: list[Printer] = []
    mem0 = rss_mb()
    work0 = worker_mb(client) if client is not None else 0.0
    try:
        return _ramp(runner, printers, rng, n, step, win, fast_share, t_start, mem0, work0, same_file, bisect, budget_s)
    finally:
        runner.close(printers, pool=False)


def _ramp(runner: Runner, printers: list[Printer], rng: np.random.Generator, n: int, step: float, win: float,
          fast_share: float, t_start: float, mem0: float, work0: float, same_file: float,
          bisect: int, budget_s: float | None) -> tuple[int, float, float]:
    client = runner.client
    shares = np.random.default_rng(rng.integers(2**32))  # its own draws: the other printer draws as without sharing
    best: tuple[int, float, float] | None = None  # the most printers that passed, their MB per printer, p99
    worst: int | None = None  # the fewest printers that failed
    halvings = 0
    fresh = False  # the window before failed: its backlog is not carried over
    t = 0.0
    joins_s = window_s = 0.0  # wall time of the joins so far, and of the last window
    while True:
        joined, t_join = len(printers), time.perf_counter()
        while len(printers) < n:  # printers join in the middle of a job: uniform phase and layer (steady state)
            period = 10.0 if rng.random() < fast_share else 60.0
            start = int(rng.integers(runner.scene.toolpath.n_layers))
            p = Printer(len(printers), period, t + rng.random() * period, start,
                        same_file=bool(shares.random() < same_file))
            runner.join(p)
            printers.append(p)
        joins_s += time.perf_counter() - t_join if len(printers) > joined else 0.0
        active = printers[:n]
        for p in active:
            if p.next_t < t:  # parked over the windows before: its next layer at its own phase from now
                p.next_t = t + (p.next_t - t) % p.period_s
            p.free_t = t if fresh else max(p.free_t, t)
        runner.wall_s = runner.charged_s = 0.0
        t_window = time.perf_counter()
        lat, events = window(active, runner, t, t + win, stop_over=P99_LIMIT_S)
        window_s = max(window_s, (time.perf_counter() - t_window) / n)  # per printer (the longest: a stopped one is short)
        t += win
        p99 = float(np.percentile(lat, 99)) if lat else float("nan")
        stopped = events is not None  # stopped early: p99 of all its frames > 2 s for certain (the figure: the run part's)
        held = rss_mb() - mem0 if client is None else worker_mb(client, work0)
        mem = held / len(printers)  # parked printers hold their jobs' memory too
        sharing = sum(p.same_file for p in active)
        print(f"N={n:5d} frames={len(lat):5d}{f'/{events} (stopped: p99 > 2 s for certain)' if stopped else ''} p50={np.percentile(lat, 50):.3f}s p99={p99:.3f}s "
              f"MB/printer={mem:.2f} cost={runner.charged_s / max(len(lat), 1) * 1e3:.0f}ms/frame "
              f"(wall {runner.wall_s / max(len(lat), 1) * 1e3:.0f}) same_file={sharing} "
              f"{'' if n == len(printers) else f'parked={len(printers) - n} '}load={os.getloadavg()[0]:.1f} "
              f"elapsed={time.perf_counter() - t_start:.0f}s", flush=True)
        passed = p99 <= P99_LIMIT_S and not stopped
        fresh = not passed
        if passed and (best is None or n > best[0]):
            best = (n, mem, p99)
        if not passed:
            worst = n if worst is None else min(worst, n)
        if worst is None:
            n = int(n * step) + 1
        elif best is None:  # the first step was already too many: start lower
            if n <= 10:
                return 0, mem, p99
            n = max(10, n // 2)
        elif halvings >= bisect or worst - best[0] <= max(1, best[0] // 50):
            return best
        else:
            n, halvings = (best[0] + worst) // 2, halvings + 1
        ahead = window_s * n + max(n - len(printers), 0) * joins_s / len(printers)  # the next window's joins and frames
        if budget_s is not None and time.perf_counter() - t_start + ahead > budget_s and best is not None:
            print(f"time budget of {budget_s:.0f} s spent: no more windows ({'no step failed yet: ' if worst is None else ''}"
                  f"the figure is a lower bound)", flush=True)
            return best


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="short windows (finishes in under 3 minutes)")
    ap.add_argument("--dask", type=int, default=0, metavar="N", help="run on a LocalCluster of N worker processes")
    ap.add_argument("--dask-speedup", type=int, default=0, metavar="N",
                    help="only compare the farm pool on N Dask worker processes with one (throughput ratio)")
    ap.add_argument("--fast-share", type=float, default=0.1, help="share of printers at one layer per 10 s")
    ap.add_argument("--window", type=float, default=None, help="farm seconds per ramp step (default 20 quick, 120)")
    ap.add_argument("--same-file", type=float, default=0.0, metavar="SHARE",
                    help="share of printers printing one file with one camera model (their references shared; "
                         "default 0: every printer its own file)")
    ap.add_argument("--bisect", type=int, default=None, metavar="K",
                    help="windows that halve the interval between the last passed and the first failed step "
                         "(default 2 with --quick, else 3)")
    ap.add_argument("--budget-s", type=float, default=None, metavar="S",
                    help="start no window predicted to end after S s of the run (default 170 with --quick: it ends "
                         "within 3 min; else none)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--march", choices=("plane", "image"), default=None,
                    help="render.march of the printers' references (default: the settings' own)")
    a = ap.parse_args(argv)
    if (not (0.0 <= a.fast_share <= 1.0) or not (0.0 <= a.same_file <= 1.0) or a.dask < 0
            or not (a.dask_speedup == 0 or 2 <= a.dask_speedup <= 64) or (a.bisect is not None and a.bisect < 0)):
        ap.error("--fast-share and --same-file must be in [0, 1], --dask >= 0, --bisect >= 0 and --dask-speedup in [2, 64]")
    t_start = time.perf_counter()
    if a.dask_speedup:
        scene = Scene(layers=speedup_layers(), march=a.march)
        ratio, same = dask_speedup(scene, a.dask_speedup)
        line = f"dask_speedup={ratio:.2f} workers={a.dask_speedup} records_identical={same}"
        print(line)
        return line
    win = a.window or (20.0 if a.quick else 120.0)
    step = 1.3 if a.quick else 1.25
    scene = Scene(layers=33, march=a.march)  # every layer of the part: a printer at one layer per 10 s prints past layer 12
    warm = Runner(scene)
    first = Printer(-1, 60.0, 0.0)
    warm.attach(first)
    warm.frame(first, 0, scene.jpeg(0, 0))  # compile and import what the first frame needs, untimed
    per_frame = float(np.mean([warm.frame(first, i, scene.jpeg(0, i))[0] for i in range(1, 7)]))
    warm.close([first])
    per_layer, rss_base = baseline(scene, 8)
    rate = (1 - a.fast_share) / 60.0 + a.fast_share / 10.0  # layers per printer per s
    print(f"farm per-frame work {per_frame * 1e3:.0f} ms CPU/frame (warm); baseline: single-printer monitor {per_layer * 1e3:.0f} ms CPU/layer, process RSS {rss_base:.0f} MB "
          f"(one monitor process per printer); layer rate {rate * 60:.2f}/min per printer; "
          f"elapsed={time.perf_counter() - t_start:.0f}s", flush=True)
    soak_mb = soak(scene, (4, 8, 16) if a.quick else (4, 16, 64), 12 if a.quick else scene.layers) if not a.dask else 0.0
    print(f"ramp starts: elapsed={time.perf_counter() - t_start:.0f}s", flush=True)
    pool = None
    workers = 1
    if a.dask:
        pool = WorkerPool(a.dask, scheduler="local")
        pool.client.run(cv2.setNumThreads, 1)  # one core per worker process, as here
        workers = a.dask
    runner = Runner(scene, pool, workers)
    n0 = max(10, int(0.7 * workers / (rate * per_frame)))  # ramp from 70 % of the estimate of one frame's cost
    try:
        bisect = a.bisect if a.bisect is not None else (2 if a.quick else 3)
        budget = a.budget_s if a.budget_s is not None else (170.0 if a.quick else None)
        best = ramp(runner, np.random.default_rng(a.seed), n0, step, win, a.fast_share, t_start, a.same_file, bisect,
                    budget)
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
          f"CPU per layer: monitor {per_layer * 1e3:.0f} ms vs farm {per_frame * 1e3:.0f} ms")
    line = f"printers_per_core={ppc:.0f} mb_per_printer={mb:.1f} p99_s={p99:.3f}"
    if a.same_file > 0:  # the figure holds for a farm where this share of the printers print one file
        line += f" same_file={a.same_file:g}"
    print(line)
    return line


def worker_mb(client, since: float = 0.0) -> float:
    """Resident set of all the cluster's worker processes, MB, minus ``since``."""
    sizes = client.run(lambda: rss_mb())
    return sum(sizes.values()) - since


def soak(scene: Scene, counts: tuple[int, ...], layers: int) -> float:
    """Memory per printer of a farm's per-printer state over a long run: the slope over several printer counts.

    Printers are added in groups until ``counts[i]`` hold a job (each with what a farm station
    holds: :class:`FarmMonitor`, its :class:`PoolPipeline` and pipeline on a local
    :class:`WorkerPool`); each new group is fed the first ``layers`` layers of the part, and the
    resident set is read after each group (all printers still open). The figure is the **slope** of
    the resident set over the printer count (least squares): what one more printer costs. The
    process's one-time costs (allocator arenas, OpenCV and NumPy buffers made on first use, the
    first group's threads) are its intercept, which a farm of hundreds spreads over all its
    printers; a single difference of two small groups (the figure before) read 8 to 21 MB for the
    same code, as the allocator kept or returned pages. The allocations of every group after the
    first are traced (:mod:`tracemalloc`: NumPy and Python blocks made and still held), and the
    larger of the two figures is returned. The slope of glibc's bytes in use (:func:`malloc_in_use_mb`:
    OpenCV's blocks too, without the free pages the allocator keeps) is printed beside them.

    Returns
    -------
    float
        MB per printer: the larger of the resident-set slope and the traced allocations held per
        printer after the first group.
    """
    gcode = b"G1 Z0.2\n"
    pool = WorkerPool(1)
    mons: list[FarmMonitor] = []
    try:
        rss = [rss_mb()]
        used = [malloc_in_use_mb()]
        ns = [0]
        traced0 = 0
        for i, count in enumerate(counts):
            if i == 1:
                tracemalloc.start()
                traced0 = tracemalloc.get_traced_memory()[0]
            new = []
            for k in range(len(mons), count):
                ctx = JobContext(f"soak/{k}", scene.toolpath, scene.camera, scene.cfg)
                new.append(FarmMonitor(VirtualPrinter(gcode), SimCamera(lambda j, k=k: scene.photo(k, j)),
                                       PoolPipeline(pool, ctx.pipeline()), PausePolicy(scene.cfg.policy),
                                       wait_for_verdict=True, faults=scene.cfg.faults,
                                       frame_quality=scene.cfg.frame_quality))  # as a farm station builds it
            mons += new
            for layer in range(layers):
                for mon in new:
                    mon.handle_trigger(SnapshotTrigger(layer, 0.2 * (layer + 1), "soak", time.monotonic()))
            rss.append(rss_mb())
            used.append(malloc_in_use_mb())
            ns.append(len(mons))
        traced = (tracemalloc.get_traced_memory()[0] - traced0) / 2**20 / max(ns[-1] - ns[1], 1)
        tracemalloc.stop()
        slope = float(np.polyfit(ns[1:], rss[1:], 1)[0]) if len(ns) > 2 else (rss[-1] - rss[0]) / max(ns[-1], 1)
        held = float(np.polyfit(ns[1:], used[1:], 1)[0]) if len(ns) > 2 else float("nan")
        print(f"long run: {'/'.join(map(str, ns[1:]))} printers' farm state (monitor, pipeline) after {layers} layers each: "
              f"resident set {' / '.join(f'{r - rss[0]:.0f}' for r in rss[1:])} MB above the start, slope "
              f"{slope:.2f} MB/printer (between the counts: "
              + ", ".join(f"{d:.2f}" for d in np.diff(rss[1:]) / np.diff(ns[1:]))
              + f"); traced allocations held {traced:.2f} MB/printer; malloc in use (all native blocks, no kept "
              f"free pages) slope {held:.2f} MB/printer", flush=True)
        return max(slope, traced)
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


#: frames each printer sends per timed phase of :func:`dask_speedup`, and the phases per pool
SPEEDUP_FRAMES, SPEEDUP_PHASES = 6, 2
#: printers of :func:`dask_speedup` start their jobs at these layers (cycled): staggered, as a farm's are
SPEEDUP_STARTS = (0, 3, 6, 9)


def speedup_layers() -> int:
    """Layers of the scene :func:`dask_speedup` needs (the latest start, its untimed frame and the timed ones)."""
    return max(SPEEDUP_STARTS) + 1 + SPEEDUP_FRAMES * SPEEDUP_PHASES


def _farm_printer(pool: WorkerPool, scene: Scene, key: str) -> FarmMonitor:
    """A printer's monitor as a farm station builds it (its camera delivers the benchmark's JPEG snapshots)."""
    cfg = scene.cfg
    ctx = JobContext(key, scene.toolpath, scene.camera, cfg)
    return FarmMonitor(VirtualPrinter(b"G1 Z0.2\n"), SnapshotBytes(), PoolPipeline(pool, ctx.pipeline(), ctx),
                       PausePolicy(cfg.policy), wait_for_verdict=True, faults=cfg.faults,
                       frame_quality=cfg.frame_quality)


def _drive(mon: FarmMonitor, scene: Scene, jpegs: list[bytes], layers: list[int], done: list[float],
           records: list) -> None:
    """One printer's frames, each sent as soon as its previous verdict came (its lane is never empty); their
    results go to ``records`` (made into dicts after the timing: that is the benchmark's work, ~20 ms a frame)."""
    assert isinstance(mon.camera, SnapshotBytes)
    for data, layer in zip(jpegs, layers, strict=True):
        mon.camera.data = data
        res = mon.handle_trigger(SnapshotTrigger(layer, float(scene.toolpath.layers[layer].z), "bench",
                                                 time.monotonic()))
        done.append(time.perf_counter())
        records.append(res)


def dask_speedup(scene: Scene, n: int) -> tuple[float, bool]:
    """Throughput of a farm on ``n`` Dask worker processes over one, and whether the records match.

    What a farm runs per frame, as it runs it: ``4 n`` printers, each a :class:`FarmMonitor` (the
    farm's :class:`PoolPipeline`, jobs pinned to workers) whose camera delivers the benchmark's
    1080p JPEG snapshots (made before, the camera's part), so the decoding, the stale-frame check,
    the camera-fault gate, the analysis, the lag check, the policy and the records are all in the
    measurement, wherever the farm runs them (the service or the workers).

    **No rounds.** A farm has no rounds: each printer sends a frame per layer, on its own clock. An
    earlier version sent one layer of every printer, waited for all of their verdicts, then sent
    the next layer (a *barrier*): each round waited for its slowest job, and a worker whose jobs
    were done idled meanwhile, which the farm never does. Here each printer has its own thread
    and sends its next frame as soon as its verdict came (a saturated farm: every printer always
    has a frame waiting), and the printers' jobs are staggered (they start at the layers
    :data:`SPEEDUP_STARTS`, so their frames are of different layers and cost different times).
    The throughput is read over the window in which **every** printer is still sending (from the
    phase's start to the moment the first printer has sent its :data:`SPEEDUP_FRAMES` frames), so
    a tail where only a few printers are left (and a worker idles) is not counted either.

    Both pools are alive at once; the phases alternate between them (1, n, n, 1 ... so both see
    the same load), each printer's first frame (which builds its worker's pipeline) is not timed.
    The records of the two pools are compared with each other (every field but timings) and, for
    the first printer, with the same frames on local threads.

    Returns
    -------
    (float, bool)
        Frames per second on ``n`` workers / on one; every record identical.
    """
    printers = 4 * n
    starts = [SPEEDUP_STARTS[k % len(SPEEDUP_STARTS)] for k in range(printers)]
    plan = [list(range(s, s + 1 + SPEEDUP_FRAMES * SPEEDUP_PHASES)) for s in starts]  # layers each printer prints
    jpegs = [[scene.jpeg(k, layer) for layer in plan[k]] for k in range(printers)]
    pools: list[WorkerPool] = []
    mons: list[list[FarmMonitor]] = []
    try:
        for w in (1, n):
            pool = WorkerPool(w, scheduler="local")
            pool.client.run(cv2.setNumThreads, 1)  # one core per worker process: OpenCV's threads would let one use both
            pools.append(pool)
            mons.append([_farm_printer(pool, scene, f"speed/{w}/{k}") for k in range(printers)])
        pids = [list(pool.client.run(os.getpid).values()) for pool in pools]
        records: list[list[list]] = [[[] for _ in range(printers)] for _ in pools]
        frames, seconds, cpu = np.zeros(2), np.zeros(2), np.zeros((2, 2))  # per pool: counted frames, s; CPU s
        with ThreadPoolExecutor(printers) as lanes:
            for j in (0, 1):  # untimed: each job's first frame (its worker builds the pipeline)
                list(lanes.map(lambda k, j=j: _drive(mons[j][k], scene, jpegs[k][:1], plan[k][:1], [],
                                                     records[j][k]), range(printers)))
            order = [(0, 1), (1, 0)]
            for phase in range(SPEEDUP_PHASES):
                lo = 1 + phase * SPEEDUP_FRAMES
                for j in order[phase % 2]:
                    done: list[list[float]] = [[] for _ in range(printers)]
                    c, t0 = _cpu(pids[j]), time.perf_counter()
                    list(lanes.map(lambda k, j=j, lo=lo, done=done: _drive(
                        mons[j][k], scene, jpegs[k][lo:lo + SPEEDUP_FRAMES], plan[k][lo:lo + SPEEDUP_FRAMES],
                        done[k], records[j][k]), range(printers)))
                    cpu[j] += _cpu(pids[j]) - c
                    t_end = min(d[-1] for d in done)  # the first printer done: until then every printer was sending
                    frames[j] += sum(t <= t_end for d in done for t in d)
                    seconds[j] += t_end - t0
        local_pool = WorkerPool(1)
        try:
            mine: list = []
            mon = _farm_printer(local_pool, scene, "speed/local/0")
            _drive(mon, scene, jpegs[0], plan[0], [], mine)
            mon.close()
        finally:
            local_pool.close()
        strip = [[[{k: v for k, v in _record(r).items() if k not in ("photo_ms", "trigger_to_pause_ms")} for r in rs]
                  for rs in pool_recs] for pool_recs in records + [[mine]]]
        same = strip[0] == strip[1] and strip[2][0] == strip[1][0]
        if not same:  # say where
            for k, (a, b) in enumerate(zip(strip[0] + strip[2], strip[1] + strip[1][:1], strict=True)):
                for r, q in zip(a, b, strict=False):
                    if r != q:
                        diff = sorted(f for f in set(r) | set(q) if r.get(f) != q.get(f))
                        print(f"dask: records differ: printer {k if k < printers else 'local 0'}, layer {r.get('layer')}: "
                              + "; ".join(f"{f}: {r.get(f)!r:.120} vs {q.get(f)!r:.120}" for f in diff), flush=True)
                        break
        loads = [sorted(p.jobs_per_worker.values()) for p in pools]
        rate = frames / seconds
        total = printers * SPEEDUP_FRAMES * SPEEDUP_PHASES
        print(f"dask: {printers} printers (jobs from layers {sorted(set(starts))}) x {SPEEDUP_FRAMES * SPEEDUP_PHASES} "
              f"timed frames; one worker {rate[0]:.2f} frames/s ({frames[0]:.0f} frames in {seconds[0]:.2f} s while every "
              f"printer sent), {n} workers {rate[1]:.2f} frames/s ({frames[1]:.0f} in {seconds[1]:.2f} s; jobs per worker "
              f"{loads[1]}); {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}", flush=True)
        print("dask: CPU per frame (service process with the scheduler + worker processes): "
              + "; ".join(f"{w} worker(s) {cpu[j, 0] / total * 1e3:.0f} + {cpu[j, 1] / total * 1e3:.0f} ms"
                          for j, w in enumerate((1, n))), flush=True)
        return float(rate[1] / rate[0]), same
    finally:
        for row in mons:
            for mon in row:
                mon.close()
                mon.pipeline.close()
        for pool in pools:
            pool.close()


if __name__ == "__main__":
    main()
