"""The per-layer work on a real Dask cluster (LocalCluster of worker processes): the same records as local threads."""

from __future__ import annotations

import hashlib
import time

import cv2
import numpy as np
import pytest

from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.farm.monitor import FarmMonitor, PoolPipeline
from layerwatch.farm.pool import WorkerPool
from layerwatch.farm.remote import JobContext
from layerwatch.farm.simcam import SimPrint
from layerwatch.gcode import read_toolpath
from layerwatch.monitor.cameras import Camera
from layerwatch.monitor.printers.base import SnapshotTrigger
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.storage.history import History

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
            thumb = pipes[k].last_thumb
            out.append((_record(res), thumb.png() if thumb is not None else None))
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


class _JpegCamera(Camera):
    """A snapshot camera of a simulated print: JPEG bytes, a black frame at ``black``, the previous layer's bytes
    again at ``repeat`` (a frozen stream)."""

    where = "test camera"

    def __init__(self, sim: SimPrint, black: int, repeat: int) -> None:
        super().__init__(retries=0, stale_check=True)
        self.sim, self.black, self.repeat, self.layer = sim, black, repeat, 0
        self.encoded_grabs = 0

    def set_layer(self, layer: int) -> None:
        self.layer = layer

    def _fetch(self) -> bytes:
        i = self.layer - 1 if self.layer == self.repeat else self.layer
        img = self.sim.frame(i)
        ok, data = cv2.imencode(".jpg", np.zeros_like(img) if i == self.black else img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        return data.tobytes()

    def grab_encoded(self):
        self.encoded_grabs += 1
        return super().grab_encoded()


class _Alerts:
    def __init__(self) -> None:
        self.sent: list[tuple[str, str, str, str | None]] = []

    def notify(self, title, message, *, level="warning", image=None, data=None, force=False):
        picture = hashlib.sha256(image.tobytes()).hexdigest() if isinstance(image, np.ndarray) else image
        self.sent.append((title, message, level, picture))


def _farm_run(pool: WorkerPool, sims, tp, cfg, layers, history) -> dict:
    """Each printer's FarmMonitor on ``pool``: its records (without timings), alerts, events and pauses."""
    faults = cfg.faults.model_copy(update={"camera_alert_after": 1})  # one unusable frame is alerted
    out = {}
    mons = {}
    for k, sim in sims.items():
        ctx = JobContext(f"farm/{k}/{id(pool)}", tp, sim.located, cfg)
        job = history.start_job(k)
        mons[k] = (FarmMonitor(VirtualPrinter(b"G1 Z0.2\n"), _JpegCamera(sim, black=4, repeat=7),
                               PoolPipeline(pool, ctx.pipeline(), ctx), PausePolicy(cfg.policy), notifier=_Alerts(),
                               history=history, job_id=job, wait_for_verdict=True, faults=faults,
                               frame_quality=cfg.frame_quality), job)
    try:
        recs = {k: [] for k in sims}
        for i in layers:  # the printers interleaved, as a farm sends them
            for k, (mon, _) in mons.items():
                res = mon.handle_trigger(SnapshotTrigger(i, float(tp.layers[i].z), "t", time.monotonic()))
                d = _record(res)
                for timing in ("photo_ms", "trigger_to_pause_ms"):
                    d.pop(timing, None)
                recs[k].append(d)
    finally:
        for mon, _ in mons.values():
            mon.close()
            mon.pipeline.close()
    for k, (mon, job) in mons.items():
        out[k] = {"records": recs[k], "alerts": mon.notifier.sent, "pauses": mon.printer.pause_count,
                  "events": [(e["kind"], e["message"]) for e in history.events(job)],
                  "encoded_grabs": mon.camera.encoded_grabs, "remote": mon.remote}
    return out


def test_dask_farm_monitor_judges_the_jpeg_on_the_worker_with_the_records_of_local_threads(tmp_path, monkeypatch):
    """The whole frame on the job's worker (JPEG decoded there, stale-frame check, gate, markers, analysis, lag
    check): the records, alerts and events of local threads; a black frame and a repeated one are camera faults,
    alerted, never a pause; the service neither decodes a frame nor runs the gate."""
    from layerwatch.monitor import cameras, frame_checks

    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    sims = {"clean": SimPrint(tp, cfg, None, 1, 1, keep=40), "spaghetti": SimPrint(tp, cfg, "spaghetti", 6, 2, keep=40)}
    # (to layer 11: with the cast-shadow test on by default the spaghetti, 2 mm beside a part 1.8 mm tall, is
    # half taken as the part's shadow for three layers and pauses at layer 10, not 7: docs/evaluation/README.md)
    layers = range(0, 12)
    history = History(tmp_path / "h.db")
    local = WorkerPool(2)
    try:
        expected = _farm_run(local, sims, tp, cfg, layers, history)
    finally:
        local.close()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:

        def not_here(*args, **kwargs):
            raise AssertionError("the service decoded a frame or ran the gate")

        monkeypatch.setattr(cameras, "decode_image", not_here)  # the worker processes have their own modules
        monkeypatch.setattr(frame_checks.FrameChecks, "gate", not_here)
        monkeypatch.setattr(LayerPipeline, "reference", not_here)  # alert overlays: the verdict brings the footprint
        got = _farm_run(WorkerPool(2, client=client), sims, tp, cfg, layers, history)
    history.close()
    for k in sims:
        assert got[k]["remote"] and not expected[k]["remote"]
        assert got[k]["encoded_grabs"] == len(layers) and expected[k]["encoded_grabs"] == 0  # JPEG bytes to the worker
        assert got[k]["records"] == expected[k]["records"]  # every field of every record
        assert got[k]["alerts"] == expected[k]["alerts"] and got[k]["events"] == expected[k]["events"]
        assert got[k]["pauses"] == expected[k]["pauses"]
    clean = got["clean"]
    faults = {r["layer"]: r for r in clean["records"] if r["status"] == "camera_fault"}
    assert sorted(faults) == [4, 7]  # the black frame; the repeated one
    assert "unusable frame" in faults[4]["message"] and "same frame twice" in faults[7]["message"]
    assert all(r["decision"] == "none" for r in faults.values()) and clean["pauses"] == 0  # never a pause
    assert sum("camera fault" in a[1] for a in clean["alerts"]) >= 2  # alerted
    assert any(isinstance(a[3], str) and len(a[3]) == 64 for a in got["spaghetti"]["alerts"])  # with the same overlay
    assert any(r["decision"] == "pause" for r in got["spaghetti"]["records"])  # the failure still pauses (can fail)


def test_a_lost_worker_costs_one_frame_and_the_job_starts_afresh_on_another(tmp_path, monkeypatch):
    """The job's worker leaves: the frame it held is a recorded, alerted error (never a pause, never a camera
    fault); the next frames go to the other worker, where the job's pipeline and frame checks are built anew."""
    from layerwatch.farm import pool as pool_mod

    monkeypatch.setattr(pool_mod, "LOST_CHECK_S", 0.5)
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    sim = SimPrint(tp, cfg, None, 1, 1, keep=12)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        pool = WorkerPool(2, client=client)
        ctx = JobContext("lost", tp, sim.located, cfg)
        mon = FarmMonitor(VirtualPrinter(b"G1 Z0.2\n"), _JpegCamera(sim, black=-1, repeat=-1),
                          PoolPipeline(pool, ctx.pipeline(), ctx), PausePolicy(cfg.policy), wait_for_verdict=True,
                          faults=cfg.faults, frame_quality=cfg.frame_quality)

        def frame(i):
            return mon.handle_trigger(SnapshotTrigger(i, float(tp.layers[i].z), "t", time.monotonic()))

        def held() -> dict:  # per worker: the job's frame checks there, and whether they hold a previous frame
            def look():
                job = __import__("layerwatch.farm.remote").farm.remote._pipelines.get("lost")
                return None if job is None or job.checks is None else job.checks.last_good is not None
            return client.run(look)

        try:
            assert [frame(i).status for i in range(3)] == ["ok"] * 3
            first = mon.pipeline.pool._pinned["lost"]
            assert held()[first] is True
            client.retire_workers([first], close_workers=True)
            for _ in range(100):
                if first not in client.scheduler_info()["workers"]:
                    break
                time.sleep(0.1)
            lost = frame(3)
            assert lost.status == "error" and "left" in lost.message and lost.decision == "notify"  # alerted
            after = [frame(i) for i in range(4, 6)]
            second = mon.pipeline.pool._pinned["lost"]
            assert second != first and [r.status for r in after] == ["ok", "ok"]
            assert list(held().values()) == [True]  # the job's frame checks now on the other worker
            assert mon.printer.pause_count == 0 and mon.report.camera_faults == 0
        finally:
            mon.close()
            mon.pipeline.close()
