"""The per-layer work on a real Dask cluster (LocalCluster of worker processes): the same records as local threads."""

from __future__ import annotations

import time

import numpy as np
import pytest

from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.farm.monitor import PoolPipeline
from layerwatch.farm.pool import WorkerPool
from layerwatch.farm.remote import JobContext
from layerwatch.farm.simcam import SimPrint
from layerwatch.gcode import read_toolpath
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.step import LayerPipeline

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore"), pytest.mark.xdist_group("servers")]
distributed = pytest.importorskip("distributed")


def _record(res) -> dict:
    d = res.to_dict()
    d.pop("timings_ms", None)
    if d.get("scene"):
        d["scene"].pop("ms", None)  # the scene channel's own timing
    return d


def _run(pool: WorkerPool, sims, tp, cfg, layers) -> tuple[list[tuple[dict, bytes | None]], dict]:
    pipes = {k: PoolPipeline(pool, LayerPipeline(tp, sim.located, cfg), JobContext(k, tp, sim.located, cfg))
             for k, sim in sims.items()}
    out = []
    for i in layers:  # two printers interleaved, as a farm sends them
        for k, sim in sims.items():
            res = pipes[k].process(sim.frame(i), i)
            out.append((_record(res), pipes[k].last_thumb))
    return out, pipes


def test_dask_cluster_gives_the_records_of_local_threads():
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    sims = {"clean": SimPrint(tp, cfg, None, 1, 1, keep=40), "spaghetti": SimPrint(tp, cfg, "spaghetti", 6, 2, keep=40)}
    layers = range(0, 12)
    local = WorkerPool(2)
    try:
        expected, _ = _run(local, sims, tp, cfg, layers)
    finally:
        local.close()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        pool = WorkerPool(2, client=client)
        got, pipes = _run(pool, sims, tp, cfg, layers)
        count = lambda: len(__import__("layerwatch.farm.remote").farm.remote._pipelines)  # noqa: E731
        ran_on = {w for w, tasks in client.run(count).items() if tasks}
        balance = sorted(pool.jobs_per_worker.values())
        for pp in pipes.values():
            pp.close()  # the jobs end: pins freed, the workers drop their pipelines
        left = 0
        for _ in range(50):
            left = sum(client.run(count).values())
            if not left:
                break
            time.sleep(0.1)  # the drop is sent, not awaited
    assert len(ran_on) == 2 and balance == [1, 1]  # the two jobs on the two worker processes
    assert left == 0 and pool.jobs_per_worker == dict.fromkeys(pool.jobs_per_worker, 0)
    assert [g[0] for g in got] == [e[0] for e in expected]  # every field of every record
    assert [g[1] for g in got] == [e[1] for e in expected]  # the same overlay thumbnails
    assert any(e[0]["anomaly_ratio"] > 0.02 for e in expected)  # the failure is in the compared records
    assert np.isfinite([e[0]["anomaly_ratio"] for e in expected]).all()


def test_local_cluster_workers_keep_the_dynamic_mmap_threshold(monkeypatch):
    """Dask's nanny would start the workers with MALLOC_TRIM_THRESHOLD_=65536 (a fixed mmap threshold: every
    large temporary of a frame faulted in anew, 2.3x the CPU per frame); the farm's LocalCluster workers run
    without it, and the service's own environment is as before."""
    import os

    from layerwatch.farm.pool import TRIM_VARIABLE

    monkeypatch.setenv(TRIM_VARIABLE, "12345")  # the service's own setting, put back after the start
    pool = WorkerPool(1, scheduler="local")
    try:
        seen = pool.client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
        assert list(seen.values()) == [None]
        assert os.environ[TRIM_VARIABLE] == "12345"
    finally:
        pool.close()
    # Dask's default, as a plain LocalCluster gets it (what the pool undoes)
    monkeypatch.delenv(TRIM_VARIABLE)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        assert list(client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_")).values()) == ["65536"]
    os.environ.pop(TRIM_VARIABLE, None)  # Dask's nanny wrote it into this process's environment
