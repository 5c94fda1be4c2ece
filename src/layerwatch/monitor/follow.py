"""``layerwatch monitor --follow``: the monitor as a service that picks up every job.

Glue between :class:`~layerwatch.monitor.jobs.JobWatcher` (which job, which file),
the per-job :class:`~layerwatch.monitor.service.Monitor` (photos, analysis, pause),
:class:`~layerwatch.monitor.artifacts.ArtifactStore` (images kept per job, retention)
and :class:`~layerwatch.monitor.parked.ParkedCamera` (frames only while parked).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import signal
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from layerwatch.errors import ConfigError, LayerwatchError
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.objects import quiet_layers, read_objects
from layerwatch.gcode.reader import load_bytes
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.pose import locate_bed
from layerwatch.geometry.settings import TopViewSettings
from layerwatch.monitor.artifacts import ArtifactStore, StoringPipeline
from layerwatch.monitor.cameras import SimCamera, open_camera
from layerwatch.monitor.hosts import JobHost, PrintJob, job_host
from layerwatch.monitor.jobs import JobWatcher
from layerwatch.monitor.notify import Notifier
from layerwatch.monitor.parked import M114Position, ParkCheck, ParkedCamera, park_spots
from layerwatch.monitor.printers.base import Printer
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.scene import load_bed_photo
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera
from layerwatch.simulate.bed_scene import start_photo
from layerwatch.storage.history import History

__all__ = ["CameraSpec", "job_camera", "fit_topview", "JobService", "run_follow"]

log = logging.getLogger("layerwatch.monitor.follow")


@dataclass(frozen=True)
class CameraSpec:
    """The camera options of ``layerwatch monitor`` (see its ``--help``)."""

    source: str = "sim"
    model: Path | None = None
    settle_s: float = 0.0
    failure: str | None = None
    onset: int = 15
    seed: int = 1
    image_size: tuple[int, int] = (1280, 720)


def job_camera(spec: CameraSpec, toolpath: Any, cfg: JobConfig) -> tuple[Any, CameraModel]:
    """The frame source and calibrated camera model for one job.

    ``spec.source == "sim"``: photos simulated from ``toolpath`` (with ``spec.failure`` injected), the
    pose found from the bed markers of the first photo as a user would calibrate, unless
    ``spec.model`` gives one. Otherwise the real camera ``spec.source`` with the model ``spec.model``.

    Raises
    ------
    ConfigError
        A real camera without ``--camera-model``.
    """
    if spec.source != "sim":
        if spec.model is None:
            raise ConfigError("--camera-model camera.toml is needed with a real camera; make one with `layerwatch calibrate`.")
        return open_camera(spec.source, settle_s=spec.settle_s), CameraModel.load(spec.model)
    tv = cfg.topview.topview()
    truth = default_camera(tv, image_size=spec.image_size)
    fails = [Failure(spec.failure, onset=spec.onset, seed=spec.seed)] if spec.failure else []
    sim = PrintSimulator(toolpath, truth, tv, fails, seed=spec.seed)
    last = toolpath.n_layers - 1
    # layer -1: the bed when the job starts (the empty-bed check), before anything is printed
    source = SimCamera(lambda i: start_photo(sim) if i < 0 else sim.frame(min(i, last)).photo, settle_s=spec.settle_s)
    model = (CameraModel.load(spec.model) if spec.model else
             locate_bed(dataclasses.replace(truth, rvec=None, tvec=None), sim.frame(0).photo, cfg.markers, tv))
    return source, model


def fit_topview(cfg: JobConfig, toolpath: Any, margin_mm: float = 30.0, min_side_mm: float = 90.0) -> JobConfig:
    """``cfg`` with the observed square centred on the job's part and large enough to hold it.

    Used for each followed job when the settings leave the top view at its built-in default
    (centred on the bed origin), as ``layerwatch analyze`` does without a job file: every
    job may sit elsewhere on the bed.

    Parameters
    ----------
    toolpath : Toolpath
        The job's parsed G-code (``bounds``: x0, y0, x1, y1 in bed mm).
    margin_mm : float
        Added to the part's larger side, mm (15 mm each side, for strands beside the part).
    min_side_mm : float
        Smallest side of the square, mm (the paper's 90 mm).
    """
    x0, y0, x1, y1 = toolpath.bounds
    side = max(min_side_mm, max(x1 - x0, y1 - y0) + margin_mm)
    view = cfg.topview.model_copy(update={"center_mm": ((x0 + x1) / 2, (y0 + y1) / 2), "width_mm": side,
                                          "height_mm": side})
    return cfg.model_copy(update={"topview": view})


class JobService:
    """Everything one followed job needs, built when the job starts.

    Parameters
    ----------
    printer : Printer
        Connector (kept open across jobs).
    host : JobHost
        The same host's job and file API.
    cfg : JobConfig
        Resolved settings.
    camera : CameraSpec
    history : History, optional
        Every job (analysed or not) gets a row; layers and events are recorded.
    store : ArtifactStore, optional
        Where each layer's images go (needs ``history``).
    notifier : Notifier, optional
    park_tolerance_mm : float or None
        Reject frames whose reported head position is farther from the park spot; ``None``: no check.
    wait_for_verdict : bool
    """

    def __init__(self, printer: Printer, host: JobHost, cfg: JobConfig, camera: CameraSpec, *,
                 history: Any = None, store: ArtifactStore | None = None, notifier: Any = None,
                 park_tolerance_mm: float | None = 1.0, wait_for_verdict: bool = False) -> None:
        self.printer, self.host, self.cfg, self.camera = printer, host, cfg, camera
        self.history, self.store, self.notifier = history, store, notifier
        self.park_tolerance_mm, self.wait_for_verdict = park_tolerance_mm, wait_for_verdict
        self.printer_name = f"{host.kind}:{str(host.http.base_url).rstrip('/')}"
        self.jobs: dict[int, tuple[int | None, Any]] = {}  # id(monitor) -> (history job id, top view)
        #: where the printer says the head is (OctoPrint: the firmware's M114 reply)
        self.position = M114Position(printer) if host.kind == "octoprint" else host.position

    def watcher(self, **kw: Any) -> JobWatcher:
        """A :class:`JobWatcher` that starts, rejects and finishes jobs through this service."""
        return JobWatcher(self.host, self.start, self.reject, on_end=self.finish, **kw)

    def start(self, job: PrintJob, gcode: bytes) -> Monitor:
        """Build the monitor of ``job`` from its downloaded G-code (raises LayerwatchError when unusable)."""
        data, _ = load_bytes(gcode)
        toolpath = read_toolpath(data)
        cfg = fit_topview(self.cfg, toolpath) if self.cfg.topview == TopViewSettings() else self.cfg
        source, model = job_camera(self.camera, toolpath, cfg)
        job_id = None
        if self.history is not None:
            job_id = self.history.start_job(self.printer_name, job.path, hashlib.sha256(gcode).hexdigest(),
                                            part=job.name, config=cfg)
        bed, note = load_bed_photo(model.bed_photo, model, given=False)  # the one `calibrate --markers` kept
        if note and model.bed_photo:
            log.warning("%s", note)
        pipeline: Any = LayerPipeline(toolpath, model, cfg, bed_photo=bed)
        if self.store is not None and job_id is not None:
            self.store.prune(keep=job_id)
            pipeline = StoringPipeline(pipeline, self.store, job_id)
        cam = source
        if self.park_tolerance_mm is not None:
            spots = park_spots(data)
            cam = ParkedCamera(source, ParkCheck(spots, self.park_tolerance_mm), self.position)
            log.info("park spots of %s: %d layers, first %s", job.name, len(spots), next(iter(spots.values()), None))
        objects = read_objects(data, toolpath)
        mon = Monitor(self.printer, cam, pipeline, PausePolicy(cfg.policy), notifier=self.notifier,
                      history=self.history, job_id=job_id,
                      wait_for_verdict=self.wait_for_verdict or cfg.policy.wait_for_verdict,
                      faults=cfg.faults, frame_quality=cfg.frame_quality,  # camera faults: alerts, never pauses
                      objects=objects, quiet_layers=quiet_layers(toolpath, objects))
        self.jobs[id(mon)] = (job_id, pipeline.topview)
        log.info("monitoring %s (%d layers, history job %s)", job.path, toolpath.n_layers, job_id)
        return mon

    def reject(self, job: PrintJob, message: str) -> None:
        """Record and announce a job that is not analysed (history row with the reason, an alert)."""
        if self.history is not None:
            jid = self.history.start_job(self.printer_name, job.path, part=job.name, config=self.cfg)
            self.history.add_event(jid, "not_analysed", message, {"file": job.path})
            self.history.end_job(jid, "not analysed")
        if self.notifier is not None:
            try:
                self.notifier.notify("layerwatch: job not analysed", message, level="warning", data={"file": job.path})
            except Exception:  # noqa: BLE001 - a notifier bug must not stop the service
                log.exception("notification failed")

    def finish(self, job: PrintJob, monitor: Monitor) -> None:
        """After a job: draw its layer stack, apply the image retention limits."""
        job_id, topview = self.jobs.pop(id(monitor), (None, None))
        if self.history is not None and job_id is not None and monitor.report.outcome != "idle":
            self.history.end_job(job_id, monitor.report.outcome)  # the watcher may have told idle apart
        if self.store is None or job_id is None:
            return
        try:
            self.store.finish(job_id, topview, self.history)
            self.store.prune()
        except (OSError, LayerwatchError) as exc:
            log.warning("images of job %s not finished: %s", job_id, exc)


def run_follow(printer: Printer, cfg: JobConfig, camera: CameraSpec, *, history: Path | None = None,
               images: Path | None = None, keep_mb: float | None = None, keep_jobs: int | None = None,
               park_tolerance_mm: float | None = 1.0, wait_for_verdict: bool = False,
               max_jobs: int | None = None, poll_s: float = 1.0) -> list[tuple[PrintJob, str]]:
    """Follow ``printer``'s jobs until SIGTERM/SIGINT (or ``max_jobs`` jobs); closes ``printer``.

    Parameters
    ----------
    history : Path, optional
        History database; images go to ``images`` (default: its folder), as ``layerwatch serve`` reads them.
    keep_mb, keep_jobs
        Image retention limits (:class:`ArtifactStore`).
    max_jobs : int, optional
        ``1`` for ``monitor`` without ``--follow`` (the current or next job, then exit).

    Returns
    -------
    list of (PrintJob, str)
        Each job handled and its outcome.
    """
    hist = store = None
    try:
        host = job_host(printer)
        if history is not None:
            hist = History(history)
            store = ArtifactStore(images or Path(history).resolve().parent, keep_mb, keep_jobs)
        service = JobService(printer, host, cfg, camera, history=hist, store=store, notifier=Notifier(cfg.notify),
                             park_tolerance_mm=park_tolerance_mm, wait_for_verdict=wait_for_verdict)
        watcher = service.watcher(poll_s=poll_s, max_jobs=max_jobs)
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: watcher.stop_event.set())
        log.info("following jobs on %s%s", service.printer_name, "" if max_jobs is None else f" ({max_jobs} job)")
        return watcher.run()
    finally:
        printer.close()
        if hist is not None:
            hist.close()
