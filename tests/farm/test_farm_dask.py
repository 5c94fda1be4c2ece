"""The per-layer work on a real Dask cluster (LocalCluster of worker processes): the same records as local threads."""

from __future__ import annotations

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

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore")]
distributed = pytest.importorskip("distributed")


def _record(res) -> dict:
    d = res.to_dict()
    d.pop("timings_ms", None)
    if d.get("scene"):
        d["scene"].pop("ms", None)  # the scene channel's own timing
    return d


def _run(pool: WorkerPool, sims, tp, cfg, layers) -> list[tuple[dict, bytes | None]]:
    pipes = {k: PoolPipeline(pool, LayerPipeline(tp, sim.located, cfg), JobContext(k, tp, sim.located, cfg))
             for k, sim in sims.items()}
    out = []
    for i in layers:  # two printers interleaved, as a farm sends them
        for k, sim in sims.items():
            res = pipes[k].process(sim.frame(i), i)
            out.append((_record(res), pipes[k].last_thumb))
    return out


def test_dask_cluster_gives_the_records_of_local_threads():
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    sims = {"clean": SimPrint(tp, cfg, None, 1, 1, keep=40), "spaghetti": SimPrint(tp, cfg, "spaghetti", 6, 2, keep=40)}
    layers = range(0, 12)
    local = WorkerPool(2)
    try:
        expected = _run(local, sims, tp, cfg, layers)
    finally:
        local.close()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        pool = WorkerPool(2, client=client)
        got = _run(pool, sims, tp, cfg, layers)
        ran_on = {w for w, tasks in client.run(lambda: len(__import__("layerwatch.farm.remote").farm.remote._pipelines)).items() if tasks}
    assert len(ran_on) >= 1  # the pipelines live in the worker processes
    assert [g[0] for g in got] == [e[0] for e in expected]  # every field of every record
    assert [g[1] for g in got] == [e[1] for e in expected]  # the same overlay thumbnails
    assert any(e[0]["anomaly_ratio"] > 0.02 for e in expected)  # the failure is in the compared records
    assert np.isfinite([e[0]["anomaly_ratio"] for e in expected]).all()
