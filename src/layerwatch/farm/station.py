"""One printer of a farm: its connector, camera, pipeline and monitor, on its own thread.

A :class:`Station` turns a :class:`~layerwatch.farm.config.PrinterSpec` into a
running :class:`~layerwatch.farm.monitor.FarmMonitor` and keeps the printer's
card (:meth:`Station.summary`) from what the monitor sees, so the dashboard
never waits on a printer host. Everything that can go wrong with one printer
(unreadable or bad G-code, a camera that cannot be opened, a host that does
not answer, a crash in set-up) becomes that printer's ``state = "error"`` with
a one-line message, and set-up is retried with backoff; the other stations
never notice.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2

from layerwatch.analysis.result import LayerResult
from layerwatch.errors import ConfigError, LayerwatchError, PrinterError
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.farm.config import PrinterSpec
from layerwatch.farm.monitor import FarmMonitor, PoolPipeline
from layerwatch.farm.pool import WorkerPool
from layerwatch.farm.remote import JobContext, Thumbnail
from layerwatch.farm.simcam import SimFrames
from layerwatch.farm.virtual import PacedVirtualPrinter
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.objects import quiet_layers, read_objects
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.gcode.reader import load_bytes
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.pose import locate_bed
from layerwatch.monitor.artifacts import ArtifactStore, StoringPipeline
from layerwatch.monitor.cameras import SimCamera, open_camera
from layerwatch.monitor.hosts import MAX_GCODE_BYTES, JobHost, PrintJob, job_host
from layerwatch.monitor.jobs import JobWatcher
from layerwatch.monitor.notify import Notifier
from layerwatch.monitor.parked import M114Position, ParkCheck, ParkedCamera, Position, park_spots
from layerwatch.monitor.printers.base import PrinterStatus, parse_trigger
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter
from layerwatch.monitor.printers.octoprint import OctoPrintPrinter
from layerwatch.monitor.service import CAMERA_FAULT
from layerwatch.pipeline.config import JobConfig, observed_square, resolve_config
from layerwatch.pipeline.policy import PausePolicy

__all__ = ["Station"]

log = logging.getLogger("layerwatch.farm")

#: a% values kept per printer for the sparkline
SPARK = 60


class _Watched:
    """The printer connector as the monitor sees it, with each status answer kept for the card."""

    def __init__(self, printer: Any, station: Station) -> None:
        self._printer, self._station = printer, station

    def status(self) -> PrinterStatus:
        try:
            st = self._printer.status()
        except LayerwatchError as exc:
            self._station.fault(f"printer unreachable: {exc}")
            raise
        self._station.seen(st)
        return st

    def __getattr__(self, name: str) -> Any:
        return getattr(self._printer, name)


class _WatchedHost(JobHost):
    """A job host whose polls keep the card's reachability (``current()``), otherwise the host itself."""

    def __init__(self, host: JobHost, station: Station) -> None:  # no HTTP client of its own: ``host``'s
        self._host, self._station = host, station
        self.kind, self.printer_name = host.kind, host.printer_name

    def current(self) -> tuple[str, PrintJob | None]:
        try:
            out = self._host.current()
        except LayerwatchError as exc:
            self._station.fault(f"printer unreachable: {exc}")
            raise
        self._station.reachable()
        return out

    def download_path(self, job: PrintJob) -> str:
        return self._host.download_path(job)

    def position(self) -> tuple[float, float, float] | None:
        return self._host.position()

    def last_outcome(self, job: PrintJob) -> str | None:
        return self._host.last_outcome(job)

    def download(self, job: PrintJob, max_bytes: int = MAX_GCODE_BYTES) -> bytes:
        return self._host.download(job, max_bytes)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._host, name)


class Station:
    """Run and describe one farm printer.

    Parameters
    ----------
    spec : PrinterSpec
    pool : WorkerPool
        The farm's shared workers.
    history : History
        Where jobs, layers and events are recorded (shared by the farm).
    sims : SimFrames
        Simulated photos shared by the farm's ``camera = "sim"`` printers.
    queue_frames : int
        Photos a printer may have waiting for a worker.
    store : ArtifactStore, optional
        Where a real printer's jobs keep their layer images (retention applied per job).
    retry_s : tuple of float
        First and largest wait between set-up attempts after an error, s.
    """

    def __init__(self, spec: PrinterSpec, pool: WorkerPool, history: Any, sims: SimFrames, *,
                 queue_frames: int = 2, store: ArtifactStore | None = None,
                 retry_s: tuple[float, float] = (2.0, 60.0)) -> None:
        self.spec, self.pool, self.history, self.sims = spec, pool, history, sims
        self.store = None if spec.is_virtual else store
        self._position: Callable[[], Position | None] | None = None  # where the host says the head is
        self.queue_frames = int(queue_frames)
        self.retry_s = retry_s
        self.stop_event = threading.Event()
        self.monitor: FarmMonitor | None = None
        self.printer: Any = None
        self._lock = threading.Lock()
        self._card: dict[str, Any] = {"state": "starting", "message": None, "job": None, "job_id": None,
                                      "layer": None, "layers": None, "ratio": None, "alarm": None}
        self._ratios: deque[float] = deque(maxlen=SPARK)
        self._thumb: Thumbnail | None = None  # the last analysed layer's (drawn when the card's picture is asked for)
        self._watcher: JobWatcher | None = None
        self._thread = threading.Thread(target=self._run, name=f"layerwatch-farm-{spec.name}", daemon=True)

    # ------------------------------------------------------------ the card
    def _set(self, **kw: Any) -> None:
        with self._lock:
            self._card.update(kw)

    def fault(self, message: str) -> None:
        """This printer is in error (one line); the card shows it until the printer answers again."""
        self._set(state="error", message=message)

    def seen(self, status: PrinterStatus) -> None:
        """The printer answered: its state (and the layer it reports) go to the card."""
        with self._lock:
            if self._card["state"] == "error" and not self._card["message"].startswith("printer unreachable"):
                return  # a camera or analysis fault stays shown until a photo is analysed again
            self._card.update(state={"finished": "idle", "cancelled": "idle"}.get(status.state, status.state),
                              message=None)

    def reachable(self) -> None:
        """The host answered a job poll: an outage shown on the card is over."""
        with self._lock:
            if self._card["state"] == "error" and self._card["message"].startswith("printer unreachable"):
                self._card.update(state="idle" if self.monitor is None else "printing", message=None)

    @property
    def thumb(self) -> bytes | None:
        """PNG of the overlay of the last analysed layer (drawn on the first request, then kept), or None."""
        thumb = self._thumb
        return thumb.png() if thumb is not None else None

    def observe(self, res: LayerResult, thumb: Thumbnail | None) -> None:
        """A layer was recorded (called by the monitor's lane)."""
        with self._lock:
            self._card["layer"] = res.layer
            if res.status == CAMERA_FAULT:  # the camera failed or its frame was unusable (never a pause)
                self._card.update(state="error", message=f"camera: {res.message}")
            elif res.status == "error":
                kind = "camera" if res.photo_ms is None else "analysis"  # no photo: the camera failed
                self._card.update(state="error", message=f"{kind}: {res.message}")
            elif self._card["state"] == "error":
                self._card.update(state="printing", message=None)
            if res.status == "ok":
                self._card["ratio"] = float(res.anomaly_ratio)
                self._ratios.append(round(float(res.anomaly_ratio), 4))
            if res.decision in ("pause", "cancel", "notify"):
                self._card["alarm"] = {"action": res.decision, "layer": res.layer, "reason": res.decision_reason}
            if thumb is not None:
                self._thumb = thumb

    def summary(self) -> dict[str, Any]:
        """The printer's card: name, state, message, job, job_id, layer, layers, ratio (last a%),
        ratios (the last :data:`SPARK`), alarm, dropped and late frames, printer URL without its query."""
        with self._lock:
            card = dict(self._card)
            card["ratios"] = list(self._ratios)
        mon = self.monitor
        card.update(name=self.spec.name, printer=self.spec.safe_printer, camera=self.spec.camera.split("?", 1)[0],
                    dropped=mon.dropped if mon else 0, late=mon.late if mon else 0, thumb=self._thumb is not None)
        return card

    # ------------------------------------------------------------ set-up
    def _config(self, toolpath: Toolpath) -> JobConfig:
        """Job settings: as ``layerwatch monitor`` resolves them, with the printer's ``settings`` as flags.

        The job file is ``config``, else the bundled example's when no G-code is given either;
        without a job file the observed square is centred on the part.
        """
        spec = self.spec
        path = spec.config or (PART_CONFIG if spec.gcode is None and not spec.printer.startswith("virtual:") else None)
        derived = observed_square(toolpath.bounds) if path is None else None
        return resolve_config(path, gcode=derived, flags=spec.settings).config

    def _gcode(self) -> tuple[Path, bytes]:
        """The job's G-code file and its bytes."""
        path = self.spec.gcode or PART_GCODE
        if self.spec.printer.startswith("virtual:"):
            path = Path(self.spec.printer[8:])
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ConfigError(f"cannot read G-code {path}: {exc.strerror}; check the gcode key.") from None
        return path, data

    def _played(self, data: bytes, cfg: JobConfig) -> bytes:
        """The G-code a virtual printer replays: with snapshot triggers (inserted when it has none)."""
        if not self.spec.is_virtual or any(parse_trigger(ln) for ln in data.decode("utf-8", "replace").splitlines()):
            return data
        return insert_snapshots(data, cfg.snapshot.model_copy(update={"profile": "octoprint"}), cfg.printer)

    def _camera(self, cfg: JobConfig, gcode: bytes, toolpath) -> tuple[Any, CameraModel]:
        spec = self.spec
        if spec.camera == "sim":
            frames = self.sims.get(gcode, toolpath, cfg, spec.failure, spec.onset, spec.seed)
            model = CameraModel.load(spec.camera_model) if spec.camera_model else frames.located
            return SimCamera(frames.frame, settle_s=spec.settle_s), model
        if spec.camera_model is None:  # the farm file's check requires it; a PrinterSpec built in code may lack it
            raise ConfigError(f"printer {spec.name!r}: camera_model is needed with camera {spec.camera.split('?', 1)[0]!r}; "
                              "make one with `layerwatch calibrate`.")
        model = CameraModel.load(spec.camera_model)
        if not model.has_pose:
            if spec.bed_photo is None:
                raise ConfigError(f"printer {spec.name!r}: camera_model has no bed pose; add bed_photo "
                                  "(a photo of the bed with its markers) or calibrate the pose.")
            photo = cv2.imread(str(spec.bed_photo), cv2.IMREAD_COLOR)
            if photo is None:
                raise ConfigError(f"printer {spec.name!r}: bed_photo {spec.bed_photo} is not an image.")
            model = locate_bed(model, photo, cfg.markers, cfg.topview.topview())
        return open_camera(spec.camera, settle_s=spec.settle_s), model

    def _printer(self, played: bytes, name: str) -> Any:
        if self.spec.is_virtual:
            printer = PacedVirtualPrinter(played, self.spec.layer_seconds, name=name)
            printer.start()
            return printer
        if self.spec.printer.startswith("octoprint://"):
            return OctoPrintPrinter(self.spec.printer)
        return MoonrakerPrinter(self.spec.printer)

    def _job(self, name: str, data: bytes) -> tuple[Toolpath, JobConfig]:
        """The toolpath and settings of a job's G-code (``ConfigError`` when it prints nothing)."""
        toolpath = read_toolpath(data)
        if toolpath.n_layers == 0:
            raise ConfigError(f"G-code {name} has no printed layers; check the gcode key or the job's file.")
        return toolpath, self._config(toolpath)

    def _build(self) -> FarmMonitor:
        """The monitor of the configured G-code (``gcode`` key, or the example part on a virtual printer)."""
        path, data = self._gcode()
        toolpath, cfg = self._job(path.name, data)
        camera, model = self._camera(cfg, data, toolpath)
        self.printer = self._printer(self._played(data, cfg), path.name)
        return self._monitor(str(path), data, toolpath, cfg, camera, model)

    def _monitor(self, path: str, data: bytes, toolpath: Toolpath, cfg: JobConfig, camera: Any,
                 model: CameraModel) -> FarmMonitor:
        """A history job and the :class:`FarmMonitor` of one job on :attr:`printer`.

        A real printer's job goes through the same path as ``layerwatch monitor --follow``
        (:class:`~layerwatch.monitor.follow.JobService`): its frames are only accepted while the
        host reports the head at the layer's park spot (:class:`ParkedCamera`, unless
        ``park_tolerance = false``), and each analysed layer's images go to the farm's
        :class:`ArtifactStore` (retention applied as the job starts and when it ends).
        """
        job = self.history.start_job(self.spec.name, path, hashlib.sha256(data).hexdigest(), config=cfg)
        ctx = JobContext(f"{self.spec.name}/{job}/{time.time_ns()}", toolpath, model, cfg,
                         share_references=True,  # a file printed again, or on a twin printer: rendered once
                         printer=self.spec.name)  # the printer's view maps kept for its next job of this file
        self._set(job=Path(path).name, job_id=job, layers=toolpath.n_layers, layer=None, ratio=None, alarm=None)
        with self._lock:
            self._ratios.clear()
        pipeline: Any = PoolPipeline(self.pool, ctx.pipeline(), ctx, with_reference=self.store is not None)
        if self.store is not None:
            self.store.prune(keep=job)
            pipeline = StoringPipeline(pipeline, self.store, job)
        if not self.spec.is_virtual and self.spec.park_tolerance_mm is not None:
            spots = park_spots(data)
            camera = ParkedCamera(camera, ParkCheck(spots, self.spec.park_tolerance_mm), self._head_position())
            log.info("printer %s: park spots of %s for %d layers", self.spec.name, Path(path).name, len(spots))
        objects = read_objects(data, toolpath)  # cancel_object cancels one of them; layers without the part are quiet
        self.monitor = FarmMonitor(_Watched(self.printer, self), camera, pipeline,
                                   PausePolicy(cfg.policy), notifier=Notifier(cfg.notify), history=self.history,
                                   job_id=job, wait_for_verdict=self.spec.wait_for_verdict or cfg.policy.wait_for_verdict,
                                   queue_frames=self.queue_frames, observe=self.observe,
                                   faults=cfg.faults, frame_quality=cfg.frame_quality,  # camera faults never pause
                                   objects=objects, quiet_layers=quiet_layers(toolpath, objects))
        return self.monitor

    def _head_position(self) -> Callable[[], Position | None]:
        """Where the host says the head is (OctoPrint: the firmware's ``M114`` reply), made once per printer."""
        if self._position is None:
            host = job_host(self.printer)
            self._position = M114Position(self.printer) if host.kind == "octoprint" else host.position
        return self._position

    def _job_done(self, monitor: FarmMonitor) -> None:
        """After a job: free its worker, draw its layer stack, apply the image retention limits."""
        close = getattr(monitor.pipeline, "close", None)  # a PoolPipeline (maybe inside a StoringPipeline)
        if close is not None:
            close()
        if self.store is None or monitor.job_id is None:
            return
        try:
            self.store.finish(monitor.job_id, monitor.pipeline.topview, self.history)
            self.store.prune()
        except (OSError, LayerwatchError) as exc:
            log.warning("printer %s: images of job %s not finished: %s", self.spec.name, monitor.job_id, exc)

    # ------------------------------------------------------------ job pick-up (real printers without `gcode`)
    def _follow(self) -> None:
        """Pick up every job the host starts (:class:`~layerwatch.monitor.jobs.JobWatcher`) until stopped."""
        self.printer = self._printer(b"", "")
        self._watcher = JobWatcher(_WatchedHost(job_host(self.printer), self), self._start_job, self._reject,
                                   on_end=self._ended, poll_s=1.0)
        if self.stop_event.is_set():
            return
        self._set(state="idle", message="waiting for a job")
        self._watcher.run()

    def _start_job(self, job: PrintJob, gcode: bytes) -> FarmMonitor:
        """The watcher saw a job start and downloaded its G-code: build its monitor."""
        data, _ = load_bytes(gcode)
        toolpath, cfg = self._job(job.name, data)
        camera, model = self._camera(cfg, data, toolpath)
        return self._monitor(job.path, data, toolpath, cfg, camera, model)

    def _reject(self, job: PrintJob, message: str) -> None:
        """A job that is not analysed (not prepared, unreadable): a history row with the reason, and the card."""
        jid = self.history.start_job(self.spec.name, job.path, part=job.name)
        self.history.add_event(jid, "not_analysed", message, {"file": job.path})
        self.history.end_job(jid, "not analysed")
        self._set(job=job.name, job_id=jid, message=f"job not analysed: {message}")

    def _ended(self, job: PrintJob, monitor: FarmMonitor) -> None:
        """A followed job ended: its verdicts can no longer act; the printer waits for the next job."""
        monitor.new_generation("job ended")
        self._job_done(monitor)
        if monitor.job_id is not None and monitor.report.outcome != "idle":
            self.history.end_job(monitor.job_id, monitor.report.outcome)
        with self._lock:
            self._card["outcome"] = monitor.report.outcome
            if self._card["state"] != "error":
                self._card["state"] = "idle"

    # ------------------------------------------------------------ running
    def start(self) -> None:
        """Start the station's thread."""
        self._thread.start()

    def _run(self) -> None:
        wait = self.retry_s[0]
        while not self.stop_event.is_set():
            try:
                if self.spec.follows_jobs:
                    self._follow()
                    return
                mon = self._build()
            except (LayerwatchError, OSError, ValueError) as exc:
                self._close_printer()
                self.fault(f"set-up failed: {exc}")
                log.warning("printer %s: set-up failed (%s); retrying in %g s", self.spec.name, exc, wait)
                self.stop_event.wait(wait)
                wait = min(wait * 2, self.retry_s[1])
                continue
            except Exception as exc:  # noqa: BLE001 - a bug in one printer's set-up must not stop the farm
                log.exception("printer %s: set-up crashed", self.spec.name)
                self._close_printer()
                self.fault(f"set-up crashed ({type(exc).__name__}: {exc}); see the service log")
                self.stop_event.wait(self.retry_s[1])
                continue
            self._watch(mon)
            return

    def _watch(self, mon: FarmMonitor) -> None:
        """Run the monitor until the job ends or the farm stops; the card keeps the outcome."""
        if self.stop_event.is_set():  # stop() ran while the monitor was being built
            mon.stop_event.set()
        try:
            report = mon.run(poll_s=0.2)
            mon.new_generation("job ended")
            with self._lock:
                self._card["outcome"] = report.outcome
                if report.outcome in ("done", "cancelled", "stopped") and self._card["state"] != "error":
                    self._card["state"] = "idle"
        except Exception as exc:  # noqa: BLE001 - a monitor bug stays with this printer
            log.exception("printer %s: monitor crashed", self.spec.name)
            self.fault(f"monitor crashed ({type(exc).__name__}: {exc}); see the service log")
        finally:
            self._job_done(mon)
            self._close_printer()

    def _close_printer(self) -> None:
        if self.printer is not None:
            try:
                self.printer.close()
            except Exception:  # noqa: BLE001 - closing is best effort
                log.exception("printer %s: close failed", self.spec.name)

    def stop(self) -> None:
        """Ask the station to stop (its monitor finishes the layer in hand)."""
        self.stop_event.set()
        if self._watcher is not None:
            self._watcher.stop_event.set()
        if self.monitor is not None:
            self.monitor.stop_event.set()

    def join(self, timeout: float | None = None) -> None:
        """Wait for the station's thread."""
        if self._thread.is_alive():
            self._thread.join(timeout)

    # ------------------------------------------------------------ buttons
    def _need_printer(self) -> Any:
        if self.printer is None:
            raise PrinterError(f"printer {self.spec.name!r} is not connected ({self._card['message'] or 'starting'}).")
        return self.printer

    def pause(self) -> None:
        """Pause the job (dashboard button)."""
        self._need_printer().pause()

    def resume(self) -> None:
        """Resume the job; photos taken before this never pause it (dashboard button)."""
        if self.monitor is not None:
            self.monitor.new_generation("resume from the dashboard")
        self._need_printer().resume()

    def cancel(self) -> None:
        """Cancel the job (dashboard button)."""
        self._need_printer().cancel()

    def status(self) -> dict[str, Any]:
        """The printer's card (:meth:`summary`), for the dashboard's printer routes."""
        return self.summary()
