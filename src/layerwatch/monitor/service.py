"""The monitor loop: printer triggers -> photo -> pipeline -> policy -> pause/notify.

The printer is held only while the photo is taken: analysis runs on one
worker thread (results stay in layer order) while the next layer prints,
unless ``wait_for_verdict`` is set. Alerts go out on a second worker thread,
in order, so a slow or dead notification target never holds up the
analysis of the next layer or a pause (the pause request is sent first, from
the analysis thread); :meth:`Monitor.close` (called by :meth:`Monitor.run`)
waits for the queued alerts.

When the job starts (:meth:`Monitor.run`, before layer 1) the pipeline's
empty-bed check runs on a fresh frame (:meth:`Monitor.check_bed`): a bed
that is not empty holds the job through the same policy and printer call as
a failing layer, with the picture of what was found in the alert.

Faults are never print failures. A printer host that does not answer, or
answers nonsense, is retried with exponential back-off capped at the poll
interval (so the monitor sees the host again within one poll interval of its
return); a camera that raises or returns no usable image, and a frame the
camera-fault gate (:func:`~layerwatch.analysis.frame_quality.assess_frame`)
refuses, give a ``camera_fault`` layer record that the pause policy does not
judge. With the gate on, two checks that need the job run beside it
(:mod:`~layerwatch.monitor.camera_checks`): the bed markers of the
calibration are looked for in each frame (a camera that moved), and a layer
whose analysis would count toward a pause is analysed once more against the
previous layer's reference (a stream that stays one layer late). A moved
camera gives ``camera_fault`` records; a frame the series shows to be one
layer late (:class:`~layerwatch.monitor.camera_checks.LateStream`: progress
since the previous frame, a slip before it; not a print that stopped growing)
is judged against the layer it shows (the lag never counts toward a pause, a
failure in the frame still does), and a consistently late stream is a camera
fault alerted once.
Printer and camera faults are logged as rate-limited warnings, written to the history as
``printer_fault``/``camera_fault`` events (and ``..._recovered`` when they end)
and notified after a grace period or a number of bad frames in a row
(:class:`~layerwatch.monitor.health.FaultSettings`); :meth:`Monitor.health`
shows the ongoing ones.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Iterable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from layerwatch.analysis.frame_quality import REPEATED_FRAME, FrameQualitySettings
from layerwatch.analysis.overlay import overlay_image
from layerwatch.analysis.result import LayerResult
from layerwatch.errors import LayerwatchError
from layerwatch.gcode.objects import ObjectMap
from layerwatch.geometry.topview import TopView
from layerwatch.monitor.camera_checks import LateCheck
from layerwatch.monitor.cameras import EncodedFrame
from layerwatch.monitor.frame_checks import CAMERA_FAULT, FrameChecks
from layerwatch.monitor.health import FaultSettings, FaultTracker
from layerwatch.monitor.printers.base import TRANSIENT_STATES, Printer, SnapshotTrigger
from layerwatch.monitor.printers.replies import RateLimitedLog
from layerwatch.pipeline.actions import ActionExecutor
from layerwatch.pipeline.policy import Decision, PausePolicy
from layerwatch.pipeline.step import Reference

__all__ = ["Monitor", "MonitorReport", "CAMERA_FAULT", "camera_error", "frame_problem", "pipeline_error"]

#: smallest side of a usable camera frame, px
MIN_FRAME_SIDE = 16

log = logging.getLogger("layerwatch.monitor")


class _Pipeline(Protocol):
    topview: TopView

    def process(self, photo: np.ndarray, layer_index: int) -> LayerResult: ...

    def reference(self, index: int) -> Reference: ...


@dataclass
class MonitorReport:
    """What happened during one monitored print."""

    results: list[LayerResult] = field(default_factory=list)
    decisions: list[Decision] = field(default_factory=list)
    pauses: int = 0
    alerts: int = 0
    outcome: str = "unknown"
    printer_faults: int = 0
    camera_faults: int = 0
    lagged_frames: int = 0

    @property
    def latencies_ms(self) -> list[float]:
        """Trigger -> pause-request latencies, ms."""
        return [r.trigger_to_pause_ms for r in self.results if r.trigger_to_pause_ms is not None]


#: printer states that end the run (once a layer was judged)
_ENDED = ("finished", "cancelled", "idle")


def _log(event: str, level: int = logging.INFO, **kv: Any) -> None:
    log.log(level, "%s %s", event, " ".join(f"{k}={v}" for k, v in kv.items()), extra={"event": event, **kv})


def frame_problem(photo: Any) -> str | None:
    """Why a camera's return value is no image to analyse, or None.

    A usable frame is a ``uint8`` ndarray of shape (H, W, 3) (or (H, W)) with both sides
    at least :data:`MIN_FRAME_SIDE` px, or an :class:`~layerwatch.monitor.cameras.EncodedFrame`
    (checked where it is decoded).
    """
    if isinstance(photo, EncodedFrame):
        return None
    if not isinstance(photo, np.ndarray):
        return f"the camera returned {type(photo).__name__}, not an image"
    if photo.dtype != np.uint8:
        return f"the camera returned a {photo.dtype} image, not 8-bit"
    if photo.ndim not in (2, 3) or photo.ndim == 3 and photo.shape[2] != 3:
        return f"the camera returned an array of shape {photo.shape}, not (H, W, 3)"
    if min(photo.shape[:2]) < MIN_FRAME_SIDE:
        return f"the camera returned a {photo.shape[1]}x{photo.shape[0]} image (empty or a placeholder)"
    return None


def camera_error(exc: BaseException) -> str:
    """The record's message for a camera that raised ``exc`` instead of giving a frame."""
    return f"camera error: {type(exc).__name__}: {exc}"


def pipeline_error(layer: int, z: float, exc: BaseException, logger: logging.Logger | None = None) -> LayerResult:
    """The ``error`` record of a layer whose analysis raised ``exc``, logged with its traceback on ``logger``
    (the monitor's by default; the monitor goes on: a pipeline bug never stops it)."""
    (logger or log).error("pipeline failed on layer %d", layer, exc_info=exc)
    return LayerResult(layer=layer, z=z, status="error", message=f"pipeline failed: {exc}")


class Monitor:
    """Watch one print.

    Parameters
    ----------
    printer : Printer
        Connector (a :class:`VirtualPrinter` that was not started is stepped by the loop).
    camera : Camera
        Photo source with ``grab()`` (and ``set_layer`` for the simulator).
    pipeline : object
        ``process(photo, layer_index) -> LayerResult``.
    policy : PausePolicy
    notifier : Notifier, optional
    history : History, optional
        With ``job_id``; layers and events are recorded.
    wait_for_verdict : bool
        Analyse before releasing the trigger (printer waits for the verdict).
    initial_backoff_s, max_backoff_s : float
        First and largest wait between printer retries, s; the wait doubles after each
        failed status poll and goes back to ``initial_backoff_s`` once the printer answers.
        ``max_backoff_s=None``: the poll interval of :meth:`run` (recovery is seen within one
        poll interval of the host's return).
    faults : FaultSettings, optional
        When faults are notified (grace period, bad frames in a row, warning interval).
    frame_quality : FrameQualitySettings, optional
        The camera-fault gate run on each frame before the pipeline; ``None`` (the default of
        this class; the ``monitor`` command always passes the job's settings) runs none. With
        it, the marker check (when ``pipeline.camera`` was calibrated with markers) and the
        lag check (when the pipeline has ``reference`` and ``top_view``) run too.
    objects : ObjectMap, optional
        The job's labelled objects (``cancel_object`` needs them; without, it pauses).
    quiet_layers : iterable of int
        Layers that print no part (start/end G-code): not judged. A ``layerwatch quiet [s=..]``
        signal (:func:`~layerwatch.monitor.printers.base.parse_signal`) suspends detection for a
        while, until ``layerwatch watch`` or its time runs out.
    executor : Executor, optional
        Where each photo's analysis and :meth:`finish_layer` run, in layer order (``submit`` and
        ``shutdown``); default one worker thread. A farm passes its bounded lane.
    """

    def __init__(self, printer: Printer, camera: Any, pipeline: _Pipeline, policy: PausePolicy | None = None,
                 *, notifier: Any = None, history: Any = None, job_id: int | None = None,
                 wait_for_verdict: bool = False, max_backoff_s: float | None = None,
                 initial_backoff_s: float = 0.1, faults: FaultSettings | None = None,
                 frame_quality: FrameQualitySettings | None = None, objects: ObjectMap | None = None,
                 quiet_layers: Iterable[int] = (), executor: Executor | None = None) -> None:
        self.printer, self.camera, self.pipeline = printer, camera, pipeline
        #: layers not judged: they print no part (start/end G-code, :func:`~layerwatch.gcode.objects.quiet_layers`)
        self.quiet_layers = frozenset(int(i) for i in quiet_layers)
        self._quiet_until = 0.0  # monotonic time a macro's quiet signal ends
        #: carries out stopping decisions, cancels single objects of ``objects``, audits
        self.actions = ActionExecutor(printer, objects, pipeline, history, job_id)
        self.policy = policy or PausePolicy()
        self.notifier, self.history, self.job_id = notifier, history, job_id
        self.wait_for_verdict = wait_for_verdict
        self.max_backoff_s = max_backoff_s
        self.initial_backoff_s = initial_backoff_s
        self.report = MonitorReport()
        self.stop_event = threading.Event()
        self._pool: Executor = executor or ThreadPoolExecutor(max_workers=1, thread_name_prefix="layerwatch-analysis")
        self._sender = ThreadPoolExecutor(max_workers=1, thread_name_prefix="layerwatch-notify")
        self._futures: list[Future] = []
        self._lock = threading.Lock()
        self._ack_seen = 0  # id of the last history event checked for dashboard acknowledgements
        self.faults = faults or FaultSettings()
        self.frame_quality = frame_quality if frame_quality is not None and frame_quality.enabled else None
        self._printer_fault = FaultTracker("printer", grace_s=self.faults.printer_grace_s)
        self._camera_fault = FaultTracker("camera", after_n=self.faults.camera_alert_after)
        self._warn = RateLimitedLog(log, self.faults.warn_interval_s)
        #: the gate, marker watch and late-stream series of this job (analysis thread only)
        self.frame_checks = FrameChecks(pipeline, self.frame_quality, self.faults.camera_alert_after, self._warn)

    def health(self) -> dict[str, dict | None]:
        """Ongoing faults: ``{"printer": {...} or None, "camera": {...} or None}`` (see :class:`Fault`)."""
        with self._lock:
            return {"printer": self._printer_fault.state(), "camera": self._camera_fault.state()}

    # ------------------------------------------------------------------ triggers
    def handle_trigger(self, trigger: SnapshotTrigger) -> LayerResult | None:
        """Take the photo for ``trigger`` and queue (or run) its analysis (a signal: quiet or watch)."""
        if trigger.signal:
            self._signal(trigger)
            return None
        _log("trigger", layer=trigger.layer, z=trigger.z, source=trigger.source)
        quiet = self._quiet_reason(trigger)
        if quiet is not None:  # start/end G-code or a queue script: no photo, nothing judged
            self._photo_done(trigger)
            res = LayerResult(layer=trigger.layer, z=trigger.z, status="skipped", message=quiet)
            if self.wait_for_verdict:
                return self.finish_layer(trigger, res)
            self._queue(self.finish_layer, trigger, res)  # keep layer order
            return res
        try:
            if hasattr(self.camera, "set_layer"):
                self.camera.set_layer(trigger.layer)
            photo = self._grab()
            problem = frame_problem(photo)
        except Exception as exc:  # noqa: BLE001 - any camera failure is a camera fault, never a crash
            problem = camera_error(exc)
        self._photo_done(trigger)
        if problem is not None:
            res = LayerResult(layer=trigger.layer, z=trigger.z, status=CAMERA_FAULT, message=problem)
            if self.wait_for_verdict:
                return self.finish_layer(trigger, res)
            self._queue(self.finish_layer, trigger, res)  # keep layer order
            return res
        t_photo = time.monotonic()
        if self.wait_for_verdict:
            return self._analyse(trigger, photo, t_photo)
        self._queue(self._analyse, trigger, photo, t_photo)
        return None

    def _grab(self) -> Any:
        """The layer's frame from the camera (a farm on a Dask cluster takes it encoded: its workers decode it)."""
        return self.camera.grab()

    def _quiet_reason(self, trigger: SnapshotTrigger) -> str | None:
        """Why ``trigger``'s layer is not judged (start/end G-code, a macro's quiet signal), or None."""
        if trigger.layer in self.quiet_layers:
            return f"layer {trigger.layer} prints no part (start/end G-code): not judged"
        left = self._quiet_until - time.monotonic()
        if left > 0:
            return f"layer {trigger.layer}: detection quiet for {left:.0f} s more (signalled by a macro)"
        return None

    def _signal(self, trigger: SnapshotTrigger) -> None:
        """``layerwatch quiet [s=..]``: suspend detection for ``z`` seconds; ``layerwatch watch``: resume now."""
        quiet = trigger.signal == "quiet"
        self._quiet_until = time.monotonic() + trigger.z if quiet else 0.0
        if quiet:  # a failure before the quiet period and one after are not in a row (after queued layers)
            if self.wait_for_verdict:
                self._forget_streaks()
            else:
                self._queue(self._forget_streaks)
        text = f"detection quiet for {trigger.z:.0f} s (signalled by the printer)" if quiet else "detection resumed"
        _log("signal", signal=trigger.signal, seconds=trigger.z, source=trigger.source)
        self.record_event(trigger.signal, text, {"seconds": trigger.z, "source": trigger.source})

    def _forget_streaks(self) -> None:
        with self._lock:
            self.policy.forget_streaks()

    def _queue(self, fn: Any, *args: Any) -> None:
        """Submit ``fn(*args)`` to the analysis executor; only the unfinished futures are kept (a long print
        would otherwise hold every layer's result twice)."""
        self._futures = [f for f in self._futures if not f.done()]
        self._futures.append(self._pool.submit(fn, *args))

    def check_bed(self) -> LayerResult | None:
        """Job start: the pipeline's empty-bed check on a fresh frame, judged by the policy (layer -1).

        ``None`` when the pipeline has no such check (or it is off, or there is no bed photo) or the
        camera gave no usable frame (a warning: the job is watched as before, never held for it).
        """
        check = getattr(self.pipeline, "check_bed", None)
        if check is None:
            return None
        try:
            if hasattr(self.camera, "set_layer"):
                self.camera.set_layer(-1)
            photo = self.camera.grab()
            problem = frame_problem(photo)
        except Exception as exc:  # noqa: BLE001 - any camera failure is a camera fault, never a hold
            problem = camera_error(exc)
        if problem is not None:
            log.warning("bed not checked at job start: %s", problem)
            return None
        res = check(photo)
        if res is None:
            return None
        _log("bed_check", status=res.status, failed=res.failed_check or "no")
        return self.finish_layer(SnapshotTrigger(layer=-1, z=0.0, source="job start"), res)

    def _photo_done(self, trigger: SnapshotTrigger) -> None:
        """Release the printer's hold for the photo (Klipper), with or without a usable frame."""
        try:
            self.printer.photo_done(trigger)
        except Exception:  # noqa: BLE001 - the hold ends by its own time-out; keep watching
            log.exception("could not tell the printer the photo of layer %d was taken", trigger.layer)

    def _lag_check(self, trigger: SnapshotTrigger, photo: np.ndarray, res: LayerResult) -> LayerResult:
        """A frame that shows the previous layer, told over the series (:meth:`LateStream.check`): judged against it.

        The returned result is then the analysis against that layer, with this trigger's layer
        and height, its message and ``frame_quality`` saying what the frame showed; otherwise
        ``res`` (its message says why a frame that looked late was judged as it is).
        """
        if not self.frame_checks.lag_checks or res.status != "ok":
            return res
        late = self.frame_checks.late(self.pipeline, photo, res, self.policy.settings)
        return self.judge_late(res, late, self.frame_checks.late_stream.count)

    def judge_late(self, res: LayerResult, late: LateCheck | None, count: int) -> LayerResult:
        """Act on the late-stream check of ``res`` (:meth:`FrameChecks.late`, ``None``: it did not run).

        ``count``: the excused frames in a row so far (the alert's figure). Returns what the policy
        judges: ``res`` (its message noting why a frame that looked late is judged as it is), or the
        frame's analysis against the layer it shows; alerts once when the lag became consistent.
        """
        if late is None:
            return res
        if late.judged is None:
            if late.why:
                res.message = (res.message + "; " if res.message else "") + late.why
            return res
        if late.alert:
            message = (f"camera lagging: {count} frames showed the layer before theirs (each judged "
                       f"against the layer it shows): {late.judged.message}")
            self.record_event("camera_fault", message, {"layer": res.layer, **late.judged.frame_quality})
            self._alert(message, res, force=True)
        if res.outside_anomalous_mm2 > 0 and hasattr(self.pipeline, "acknowledge"):
            with self._lock:  # as Monitor.acknowledge: the change beside the print was the previous layer
                self.pipeline.acknowledge()
        self.report.lagged_frames += 1
        self._warn.warning("lag", "layer %d: %s", res.layer, late.judged.message)
        return late.judged

    def _analyse(self, trigger: SnapshotTrigger, photo: np.ndarray, t_photo: float) -> LayerResult:
        res = self.frame_checks.gate(trigger.layer, trigger.z, photo)
        if res is not None:
            return self.finish_layer(trigger, res)
        try:
            res = self.pipeline.process(photo, trigger.layer)
        except Exception as exc:  # noqa: BLE001 - a pipeline bug must not stop the monitor
            res = pipeline_error(trigger.layer, trigger.z, exc)
        res.photo_ms = round((t_photo - trigger.time) * 1000, 1)
        res = self._lag_check(trigger, photo, res)
        top = getattr(self.pipeline, "last_top", None) if res.status == "ok" else None  # one analysis thread
        return self.finish_layer(trigger, res, top)

    def finish_layer(self, trigger: SnapshotTrigger, res: LayerResult, top: np.ndarray | None = None) -> LayerResult:
        """Judge a layer's record with the policy, act on it (pause or cancel, alerts) and record it.

        The step after each photo's analysis (or camera fault), on the analysis executor in layer
        order; the hook a subclass extends (the farm's monitor keeps verdicts on photos older than
        an operator action from acting). ``top``: the photo's grey top view, for alert overlays.
        """
        with self._lock:
            decision = self.policy.update(res)
            if decision.stops:  # pause, cancel, cancel one object or a host command (pipeline/actions.py)
                done = self.actions.execute(decision, self.policy)
                decision = done.decision
                if done.ok:
                    res.trigger_to_pause_ms = round((time.monotonic() - trigger.time) * 1000, 1)
                    self.report.pauses += 1
                else:  # the host failed: say so, keep watching
                    self._alert(f"could not {decision.action} the printer: {done.error}", res, level="critical",
                                force=True)
            res.decision, res.decision_reason = decision.action, decision.reason
            self.report.results.append(res)
            self.report.decisions.append(decision)
            _log("layer", layer=res.layer, status=res.status, ratio=round(float(res.anomaly_ratio), 4),
                 action=decision.action, latency_ms=res.trigger_to_pause_ms)
            self._record(res, decision)
            self._track_camera(res)
            if decision.action != "none":
                self._alert(decision.reason, res, level="critical" if decision.stops else "warning",
                            force=decision.stops, image=self._overlay(res, top))
        return res

    def _overlay(self, res: LayerResult, top: np.ndarray | None) -> np.ndarray | str | None:
        """The failing regions over the photo's top view for an alert (RGB), or a saved overlay's path."""
        checks = getattr(self.pipeline, "checks", None)
        found = getattr(checks, "image", None)
        if res.failed_check and found is not None:  # what the check found
            return found
        if res.images.get("overlay"):  # stored by StoringPipeline, relative to its image folder
            return str(Path(getattr(self.pipeline, "image_root", ""), res.images["overlay"]))
        if top is None or res.heatmap is None:
            return None
        try:
            foot = self._footprint(res.layer)
            return overlay_image(top, res, self.pipeline.topview, foot)
        except (LayerwatchError, ValueError, AttributeError) as exc:  # the alert goes out without a picture
            log.warning("overlay for layer %d not drawn: %s", res.layer, exc)
            return None

    def _footprint(self, layer: int) -> np.ndarray:
        """Top-view footprint of layer ``layer`` (bool, (H, W)), for an alert's overlay."""
        return self.pipeline.reference(layer).footprint

    def _track_camera(self, res: LayerResult) -> None:
        """Open, count, notify or close the camera-fault episode after one layer (lock held)."""
        if res.status != CAMERA_FAULT:
            ended = self._camera_fault.recovered() if res.status != "error" else None
            if ended is not None:
                self._warn.reset("camera")
                _log("camera_recovered", frames=ended.count)
                self.record_event("camera_recovered", f"camera delivers usable frames again after {ended.count} bad one(s)",
                            {"layer": res.layer, "frames": ended.count})
                if ended.notified:
                    self._alert(f"camera recovered: usable frames again from layer {res.layer}", res, level="info",
                                force=True)
            return
        self.report.camera_faults += 1
        self._stream_interrupted()  # the stream may come back one layer late
        started, notify = self._camera_fault.failed(res.message)
        self._warn.warning("camera", "camera fault on layer %d (never a pause): %s", res.layer, res.message)
        if started:
            self.record_event("camera_fault", res.message, {"layer": res.layer, **res.frame_quality})
        if notify:
            n = self._camera_fault.current.count if self._camera_fault.current else 0
            still = ("; if the printer is printing, the print may have stopped growing (clog, filament run-out): "
                     "look at it" if REPEATED_FRAME in res.message else "")
            self._alert(f"camera fault: {n} unusable frames in a row, layers are not being checked: {res.message}"
                        f"{still}", res, force=True)

    def _stream_interrupted(self) -> None:
        """A frame was unusable: the late-stream series may come back one layer late (analysis thread)."""
        self.frame_checks.late_stream.interrupted()

    def record_event(self, kind: str, message: str, data: dict | None = None) -> None:
        """Append an event to this job's history (none without a history; a failed write is a warning)."""
        if self.history is None or self.job_id is None:
            return
        try:
            self.history.add_event(self.job_id, kind, message, data)
        except LayerwatchError as exc:
            log.warning("history write failed: %s", exc)

    def _record(self, res: LayerResult, decision: Decision) -> None:
        if self.history is None or self.job_id is None:
            return
        try:
            self.history.add_layer(self.job_id, res)
            if decision.action != "none":
                self.history.add_event(self.job_id, decision.action, decision.reason,
                                       {"layer": res.layer, "kind": decision.kind} if decision.kind else {"layer": res.layer})
        except LayerwatchError as exc:
            log.warning("history write failed: %s", exc)

    def _alert(self, message: str, res: LayerResult | None = None, *, level: str = "warning", force: bool = False,
               image: np.ndarray | str | None = None) -> None:
        self.report.alerts += 1
        log.warning("alert: %s", message)
        if self.notifier is None:
            return
        if image is None and res is not None:
            image = res.images.get("overlay")
        args = (f"layerwatch: {message.split(':')[0]}", message)
        kw = {"level": level, "image": image, "data": {"layer": res.layer if res else None}, "force": force}
        try:
            self._sender.submit(self._send, args, kw)
        except RuntimeError:  # the sender is closed (close() ran): send it from here rather than lose it
            self._send(args, kw)

    def _send(self, args: tuple, kw: dict) -> None:
        try:
            self.notifier.notify(*args, **kw)
        except Exception:  # noqa: BLE001 - a notifier bug must not stop the monitor
            log.exception("notification failed: %s", args[0])

    def close(self) -> None:
        """Finish the queued analysis and send every queued alert (blocks until they are out)."""
        self._pool.shutdown(wait=True)
        self._sender.shutdown(wait=True)

    def acknowledge(self, source: str = "resume") -> None:
        """The operator accepted the regions seen so far (``source``: ``"resume"`` or ``"dashboard"``).

        They do not trigger again unless they grow (see :meth:`PausePolicy.acknowledge`).
        """
        with self._lock:
            before = len(self.policy.acknowledged)
            self.policy.acknowledge()
            if hasattr(self.pipeline, "acknowledge"):  # the scene channel stops reporting what was accepted
                self.pipeline.acknowledge()
            n = len(self.policy.acknowledged) - before
        _log("acknowledged", source=source, regions=n)
        if self.history is not None and self.job_id is not None:
            try:
                self.history.add_event(self.job_id, "acknowledged",
                                       f"policy accepted {n} region(s) ({source}); they pause again only if they grow",
                                       {"source": source, "regions": n})
            except LayerwatchError as exc:
                log.warning("history write failed: %s", exc)

    def poll_acknowledgements(self) -> int:
        """Apply ``acknowledge`` events the dashboard wrote to this job's history since the last call.

        Returns
        -------
        int
            Number of acknowledgements applied (0 without a history).
        """
        if self.history is None or self.job_id is None:
            return 0
        try:
            events = self.history.events(self.job_id, after=self._ack_seen)
        except LayerwatchError as exc:
            log.warning("history read failed: %s", exc)
            return 0
        if not events:
            return 0
        self._ack_seen = events[-1]["id"]
        n = sum(e["kind"] == "acknowledge" for e in events)
        if n:
            self.acknowledge(source="dashboard")
        return n

    # ------------------------------------------------------------------ loop
    def run(self, *, poll_s: float = 0.2, install_signals: bool = False) -> MonitorReport:
        """Run until the print ends or :attr:`stop_event` is set (SIGTERM/SIGINT when ``install_signals``).

        No printer or camera fault ends the run: a failed poll (unreachable host, time-out,
        malformed reply, a connector bug) is retried with back-off up to
        ``max_backoff_s`` (default ``poll_s``) until the host answers again.
        """
        if install_signals and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: self.stop_event.set())
        cap = self.max_backoff_s if self.max_backoff_s is not None else max(poll_s, self.initial_backoff_s)
        backoff = self.initial_backoff_s
        settled = last_seen = ""  # last settled state (not pausing/resuming/cancelling), last state seen
        try:
            self.check_bed()
            while not self.stop_event.is_set():
                self.poll_acknowledgements()  # the dashboard's acknowledge button (shared history)
                try:
                    if getattr(self.printer, "needs_stepping", False):  # a duck-typed connector prints on its own
                        if self._step():
                            break
                        continue
                    for trig in self.printer.poll_triggers():
                        self.handle_trigger(trig)
                    state = self.printer.status().state
                    if state in _ENDED:  # the last layers' triggers came in while the photos were taken or
                        for trig in self.printer.poll_triggers():  # the state read: judged, not dropped
                            self.handle_trigger(trig)
                except Exception as exc:  # noqa: BLE001 - a host fault (or a connector bug) is retried, never fatal
                    self._printer_failed(exc, backoff, cap)
                    self.stop_event.wait(backoff)
                    backoff = min(backoff * 2, cap)
                    continue
                backoff = self.initial_backoff_s
                self._printer_answered(state)
                settled = self._follow_state(state, settled, last_seen)
                last_seen = state
                if state in _ENDED and any(r.layer >= 0 for r in self.report.results):
                    break
                self.stop_event.wait(poll_s)
        finally:
            self.close()  # finish the current layer's record and send its alerts
            self.report.outcome = self._outcome()
            if self.history is not None and self.job_id is not None:
                try:
                    self.history.end_job(self.job_id, self.report.outcome)
                except LayerwatchError as exc:
                    log.warning("history end_job failed: %s", exc)
        return self.report

    def _step(self) -> bool:
        """One step of a caller-driven printer (the virtual replay); True when the run should end.

        The replay has no clock: a real layer takes far longer than its analysis, so the next layer is
        replayed only once the queued analyses are done (else a pause could arrive after the replay
        had run to the end of the file, as it did when the analysis took a few seconds more)."""
        futures_wait(self._futures)
        trig = self.printer.step_to_next_trigger()
        if trig is not None:
            self.printer.poll_triggers()
            self.handle_trigger(trig)
        if self.printer.status().state == "paused":  # no operator at a virtual printer
            self._pool.shutdown(wait=True)
            return True
        return trig is None and self.printer.status().state in ("finished", "cancelled")

    def _follow_state(self, state: str, settled: str, last_seen: str) -> str:
        """Log transient states and take an operator's resume as an acknowledgement; the new settled state."""
        if state in TRANSIENT_STATES:
            # pausing/resuming/cancelling: neither paused nor resumed yet; ``settled`` keeps the
            # last settled state, so "pausing -> printing" is no operator resume
            if state != last_seen:
                _log("transient", state=state)
            return settled
        if settled and state != settled and state in ("paused", "printing", "cancelled"):
            self.actions.state_changed(settled, state)  # audited with its source
        if settled == "paused" and state == "printing" and self.policy.halted:
            _log("resumed", layer=self.report.results[-1].layer if self.report.results else None)
            self.acknowledge()  # the operator resumed: accept what was seen
        return state

    def _printer_failed(self, exc: Exception, retry_s: float, cap: float) -> None:
        """One failed poll: count it, warn (rate-limited), record the episode, notify after the grace period."""
        error = str(exc) if isinstance(exc, LayerwatchError) else f"{type(exc).__name__}: {exc}"
        if not isinstance(exc, LayerwatchError):
            log.debug("unexpected printer error", exc_info=exc)
        self.report.printer_faults += 1
        with self._lock:
            started, notify = self._printer_fault.failed(error)
            count = self._printer_fault.current.count if self._printer_fault.current else 0
        _log("printer_unreachable", logging.DEBUG, retry_s=retry_s, error=error)
        self._warn.warning("printer", "printer fault (never a pause), retrying every <= %g s: %s", cap, error)
        if started:
            self.record_event("printer_fault", error, {"retry_s": retry_s})
        if notify:
            self._alert(f"printer unreachable for {self.faults.printer_grace_s:g} s ({count} failed polls), "
                        f"retrying every <= {cap:g} s; layers are not being checked: {error}", force=True)

    def _printer_answered(self, state: str) -> None:
        """The host answered: close the fault episode, if any."""
        with self._lock:
            ended = self._printer_fault.recovered()
        if ended is None:
            return
        self._warn.reset("printer")
        after = round(time.monotonic() - ended.started, 2)
        _log("printer_reconnected", after_s=after, failed_polls=ended.count, state=state)
        self.record_event("printer_recovered", f"printer answers again after {after} s ({ended.count} failed polls)",
                    {"after_s": after, "failed_polls": ended.count, "state": state})
        if ended.notified:
            self._alert(f"printer reachable again after {after:g} s (state {state})", level="info", force=True)

    def _outcome(self) -> str:
        try:
            state = self.printer.status().state
        except Exception:  # noqa: BLE001 - the host is gone at the end: the outcome is unknown, not a crash
            return "unknown"
        return {"finished": "done", "cancelled": "cancelled", "paused": "paused"}.get(
            state, "stopped" if self.stop_event.is_set() else state)
