"""A farm printer's state stays bounded over a long print, and the Dask pool balances and frees its jobs.

Counted in objects and bytes, never in time.
"""

from __future__ import annotations

import gc
import time
import tracemalloc
import zlib

import numpy as np
import pytest

from layerwatch.analysis.result import LayerResult
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.farm.monitor import RESULTS_KEPT, FarmMonitor, PoolPipeline
from layerwatch.farm.pool import WorkerLost, WorkerPool
from layerwatch.farm.remote import JobContext, analyse_on
from layerwatch.farm.simcam import SimPrint
from layerwatch.gcode import read_toolpath
from layerwatch.monitor.printers.base import SnapshotTrigger
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.simulate import PrintSimulator, default_camera
from layerwatch.storage.history import History

#: the issue's target: 500 printers in 5 GB
MB_PER_PRINTER = 10.0
#: what a printer's pipeline may hold as arrays: the target less a fifth for the rest of its state
#: (monitor, last good frame, Python objects) and the allocator
PIPELINE_MB = 0.8 * MB_PER_PRINTER


class _Camera:
    def grab(self):
        return np.zeros((32, 32, 3), np.uint8)


class _Pipeline:
    """Every layer 'ok' with a 64 x 64 heatmap (what makes a record weigh ~33 kB)."""

    topview = None

    def process(self, photo, layer):
        return LayerResult(layer=layer, z=0.2 * (layer + 1), status="ok", anomaly_ratio=0.0,
                           heatmap=np.zeros((64, 64)))


def _alive(cls) -> int:
    gc.collect()
    return sum(isinstance(o, cls) for o in gc.get_objects())


def test_farm_monitor_keeps_a_bounded_number_of_records_over_a_long_print(tmp_path):
    h = History(tmp_path / "h.db")
    job = h.start_job("p01")
    mon = FarmMonitor(VirtualPrinter(b"G1 Z0.2\n", name="t.gcode"), _Camera(), _Pipeline(), PausePolicy(),
                      history=h, job_id=job, queue_frames=2)
    before = _alive(LayerResult)
    for layer in range(400):
        mon.handle_trigger(SnapshotTrigger(layer, 0.2 * (layer + 1)))
        while mon._lane.pending:  # every frame analysed (dropping is not under test here)
            time.sleep(0.001)
    mon.close()
    held = _alive(LayerResult) - before
    assert len(mon.report.results) == RESULTS_KEPT and len(mon.report.decisions) == RESULTS_KEPT
    assert mon.report.results[-1].layer == 399
    assert held <= RESULTS_KEPT + 4, held  # not one record per layer (400)
    assert len(mon._futures) <= 4
    assert h.latest_layer(job).layer == 399  # every layer is still in the history
    h.close()


def test_farm_pipeline_memory_does_not_grow_with_layers():
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    sim = SimPrint(tp, cfg, None, 1, 1, keep=16)
    photos = [sim.frame(i) for i in range(16)]
    pipe = JobContext("mem", tp, sim.located, cfg).pipeline()
    analyse_on(pipe, photos[0], 0)
    tracemalloc.start()
    try:
        for i in range(1, 4):
            analyse_on(pipe, photos[i], i)
        gc.collect()
        early = tracemalloc.get_traced_memory()[0]
        for i in range(4, 16):
            analyse_on(pipe, photos[i], i)
        gc.collect()
        late = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    # 12 more layers: a remap table per layer height (~2.5 MB each) would add ~30 MB
    assert late - early < 3e6, (late - early) / 1e6


def _array_bytes(obj, seen: set[int]) -> dict[str, int]:
    """``{attribute path: nbytes}`` of every NumPy array reachable from ``obj`` through attributes (slots
    included) and containers, each buffer counted once (views count their base; ids in ``seen`` are skipped)."""
    out: dict[str, int] = {}
    stack = [(obj, "")]
    while stack:
        o, path = stack.pop()
        if id(o) in seen or isinstance(o, (str, bytes, int, float, bool, type(None), type)):
            continue
        seen.add(id(o))
        if isinstance(o, np.ndarray):
            base = o
            while isinstance(base.base, np.ndarray):
                base = base.base
            if base is o or id(base) not in seen:
                seen.add(id(base))
                out[path] = base.nbytes
            continue
        if isinstance(o, dict):
            stack += [(v, f"{path}[{k!r}]") for k, v in o.items()]
        elif isinstance(o, (list, tuple, set, frozenset)):
            stack += [(v, f"{path}[{i}]") for i, v in enumerate(o)]
        else:
            if hasattr(o, "__dict__"):
                stack += [(v, f"{path}.{k}") for k, v in vars(o).items()]
            slots = [n for c in type(o).__mro__ for n in getattr(c, "__slots__", ()) if hasattr(o, n)]
            stack += [(getattr(o, n), f"{path}.{n}") for n in slots]  # e.g. a Reference
    return out


@pytest.mark.slow
def test_a_farm_pipeline_holds_at_most_8_mb_of_arrays_between_layers():
    """What a printer's pipeline keeps between layers of a 1080p camera (scene model, warper, renderer, checks,
    references), counted as array bytes: the job's toolpath, camera and settings are shared, not counted."""
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    tv = cfg.topview.topview()
    camera = default_camera(tv, image_size=(1920, 1080))
    sim = PrintSimulator(tp, camera, tv, [], seed=1)
    pool = WorkerPool(1)
    farm = PoolPipeline(pool, JobContext("mem", tp, camera, cfg).pipeline())
    pipe = farm.local
    try:
        for i in range(8):  # as a farm monitor: each layer analysed on the pool, then recorded
            assert farm.process(sim.frame(i).photo, i).status == "ok"
            farm.layer_done()
    finally:
        pool.close()
    seen: set[int] = set()
    for shared in (pipe.toolpath, pipe.camera, pipe.config, pipe.topview):
        _array_bytes(shared, seen)
    held = _array_bytes(pipe, seen)
    total = sum(held.values()) / 2**20
    top = sorted(held.items(), key=lambda kv: -kv[1])[:6]
    assert total <= PIPELINE_MB, f"{total:.1f} MB: " + ", ".join(f"{k} {v / 2**20:.1f}" for k, v in top)
    assert pipe.scene is not None and pipe.scene.expected is not None  # the scene channel is on and has a baseline


class _FakeClient:
    """Enough of ``distributed.Client`` for the pool's worker choice: two workers, counted scheduler queries."""

    def __init__(self, workers):
        self.workers = dict.fromkeys(workers, {"nthreads": 1})
        self.queries = 0
        self.submitted = []

        self.scheduler = self  # the scheduler's rpc: identity()

    def identity(self, n_workers=0):
        self.queries += 1
        return {"workers": dict(self.workers) if n_workers else {}}  # as a scheduler: no workers unless asked

    def sync(self, fn, *args, **kwargs):
        return fn(*args, **kwargs)

    def submit(self, fn, *args, workers=None, **kw):
        self.submitted.append((fn.__name__, args, workers))

        class _Done:
            def result(self, timeout=None):
                return fn.__name__

        return _Done()


def test_dask_pool_balances_jobs_frees_them_and_does_not_query_the_scheduler_per_frame():
    client = _FakeClient(["tcp://a:1", "tcp://b:1"])
    pool = WorkerPool(2, client=client)
    # keys that all hash to the same worker (what crc32 pinning gave): still spread evenly
    keys = [k for k in (f"p{i:02d}/1" for i in range(200)) if zlib.crc32(k.encode()) % 2 == 0][:6]
    for _ in range(5):
        for k in keys:
            pool.run(analyse_on, None, None, 0, key=k)
    assert sorted(pool.jobs_per_worker.values()) == [3, 3]
    assert client.queries == 1  # cached: 30 frames, one query
    first = {k: pool._worker_for(k) for k in keys}
    pool.release(keys[0])
    assert client.submitted[-1][0] == "forget_pipeline" and client.submitted[-1][2] == [first[keys[0]]]
    assert sum(pool.jobs_per_worker.values()) == 5
    # a worker leaves: its jobs move to the one left, the others stay where they were
    gone = first[keys[1]]
    del client.workers[gone]
    pool._seen_at = float("-inf")  # the cached list is REFRESH_S old
    moved = pool._worker_for(keys[1])
    assert moved != gone and pool._worker_for(keys[2]) in client.workers
    client.workers.clear()
    pool._seen_at = float("-inf")
    try:
        pool._worker_for("new")
    except WorkerLost as exc:
        assert "dask worker" in str(exc)
    else:
        raise AssertionError("no worker must raise WorkerLost")
