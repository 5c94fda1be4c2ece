"""The monitor loop: printer triggers -> photo -> pipeline -> policy -> pause/notify.

The printer is held only while the photo is taken: analysis runs on one
worker thread (results stay in layer order) while the next layer prints,
unless ``wait_for_verdict`` is set. Alerts go out on a second worker thread,
in order, so a slow or dead notification target never holds up the
analysis of the next layer or a pause (the pause request is sent first, from
the analysis thread); :meth:`Monitor.close` (called by :meth:`Monitor.run`)
waits for the queued alerts. Camera, pipeline and printer failures are
alerted and logged, never turned into a pause; the printer connection is
retried with exponential backoff.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from layerwatch.analysis.result import LayerResult
from layerwatch.errors import CameraError, LayerwatchError, PrinterError
from layerwatch.monitor.printers.base import TRANSIENT_STATES, Printer, SnapshotTrigger
from layerwatch.pipeline.policy import Decision, PausePolicy

__all__ = ["Monitor", "MonitorReport"]

log = logging.getLogger("layerwatch.monitor")


class _Pipeline(Protocol):
    def process(self, photo: np.ndarray, layer_index: int) -> LayerResult: ...


@dataclass
class MonitorReport:
    """What happened during one monitored print."""

    results: list[LayerResult] = field(default_factory=list)
    decisions: list[Decision] = field(default_factory=list)
    pauses: int = 0
    alerts: int = 0
    outcome: str = "unknown"

    @property
    def latencies_ms(self) -> list[float]:
        """Trigger -> pause-request latencies, ms."""
        return [r.trigger_to_pause_ms for r in self.results if r.trigger_to_pause_ms is not None]


def _log(event: str, **kv: Any) -> None:
    log.info("%s %s", event, " ".join(f"{k}={v}" for k, v in kv.items()), extra={"event": event, **kv})


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
    """

    def __init__(self, printer: Printer, camera: Any, pipeline: _Pipeline, policy: PausePolicy | None = None,
                 *, notifier: Any = None, history: Any = None, job_id: int | None = None,
                 wait_for_verdict: bool = False, max_backoff_s: float = 30.0,
                 initial_backoff_s: float = 1.0) -> None:
        self.printer, self.camera, self.pipeline = printer, camera, pipeline
        self.policy = policy or PausePolicy()
        self.notifier, self.history, self.job_id = notifier, history, job_id
        self.wait_for_verdict = wait_for_verdict
        self.max_backoff_s = max_backoff_s
        self.initial_backoff_s = initial_backoff_s
        self.report = MonitorReport()
        self.stop_event = threading.Event()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="layerwatch-analysis")
        self._sender = ThreadPoolExecutor(max_workers=1, thread_name_prefix="layerwatch-notify")
        self._futures: list[Future] = []
        self._lock = threading.Lock()
        self._ack_seen = 0  # id of the last history event checked for dashboard acknowledgements

    # ------------------------------------------------------------------ triggers
    def handle_trigger(self, trigger: SnapshotTrigger) -> LayerResult | None:
        """Take the photo for ``trigger`` and queue (or run) its analysis."""
        _log("trigger", layer=trigger.layer, z=trigger.z, source=trigger.source)
        if hasattr(self.camera, "set_layer"):
            self.camera.set_layer(trigger.layer)
        try:
            photo = self.camera.grab()
        except (CameraError, OSError) as exc:
            res = LayerResult(layer=trigger.layer, z=trigger.z, status="error", message=str(exc))
            self._finish(trigger, res)
            return res
        t_photo = time.monotonic()
        if self.wait_for_verdict:
            return self._analyse(trigger, photo, t_photo)
        self._futures.append(self._pool.submit(self._analyse, trigger, photo, t_photo))
        return None

    def _analyse(self, trigger: SnapshotTrigger, photo: np.ndarray, t_photo: float) -> LayerResult:
        try:
            res = self.pipeline.process(photo, trigger.layer)
        except Exception as exc:  # noqa: BLE001 - a pipeline bug must not stop the monitor
            log.exception("pipeline failed on layer %d", trigger.layer)
            res = LayerResult(layer=trigger.layer, z=trigger.z, status="error", message=f"pipeline failed: {exc}")
        res.photo_ms = round((t_photo - trigger.time) * 1000, 1)
        top = getattr(self.pipeline, "last_top", None) if res.status == "ok" else None  # one analysis thread
        return self._finish(trigger, res, top)

    def _finish(self, trigger: SnapshotTrigger, res: LayerResult, top: np.ndarray | None = None) -> LayerResult:
        with self._lock:
            decision = self.policy.update(res)
            if decision.stops:
                try:
                    (self.printer.pause if decision.action == "pause" else self.printer.cancel)()
                    res.trigger_to_pause_ms = round((time.monotonic() - trigger.time) * 1000, 1)
                    self.report.pauses += 1
                except LayerwatchError as exc:
                    self._alert(f"could not {decision.action} the printer: {exc}", res)
            res.decision, res.decision_reason = decision.action, decision.reason
            self.report.results.append(res)
            self.report.decisions.append(decision)
            _log("layer", layer=res.layer, status=res.status, ratio=round(float(res.anomaly_ratio), 4),
                 action=decision.action, latency_ms=res.trigger_to_pause_ms)
            self._record(res, decision)
            if decision.action != "none":
                self._alert(decision.reason, res, level="critical" if decision.stops else "warning",
                            force=decision.stops, image=self._overlay(res, top))
        return res

    def _overlay(self, res: LayerResult, top: np.ndarray | None) -> np.ndarray | str | None:
        """The failing regions over the photo's top view for an alert (RGB), or a saved overlay's path."""
        if res.images.get("overlay"):  # stored by StoringPipeline, relative to its image folder
            return str(Path(getattr(self.pipeline, "image_root", ""), res.images["overlay"]))
        if top is None or res.heatmap is None:
            return None
        try:
            from layerwatch.analysis.overlay import overlay_image

            foot = self.pipeline.reference(res.layer).footprint
            return overlay_image(top, res, self.pipeline.topview, foot)
        except (LayerwatchError, ValueError, AttributeError) as exc:  # the alert goes out without a picture
            log.warning("overlay for layer %d not drawn: %s", res.layer, exc)
            return None

    def _record(self, res: LayerResult, decision: Decision) -> None:
        if self.history is None or self.job_id is None:
            return
        try:
            self.history.add_layer(self.job_id, res)
            if decision.action != "none":
                self.history.add_event(self.job_id, decision.action, decision.reason, {"layer": res.layer})
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
        """Run until the print ends or :attr:`stop_event` is set (SIGTERM/SIGINT when ``install_signals``)."""
        if install_signals and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: self.stop_event.set())
        step = getattr(self.printer, "step_to_next_trigger", None)
        driven = step is not None and getattr(self.printer, "_thread", None) is None
        backoff = self.initial_backoff_s
        outage: tuple[float, int] | None = None  # (start, failed polls) while the printer is unreachable
        prev_state = last_seen = ""
        try:
            while not self.stop_event.is_set():
                self.poll_acknowledgements()  # the dashboard's acknowledge button (shared history)
                if driven:
                    trig = step()
                    if trig is not None:
                        self.printer.poll_triggers()
                        self.handle_trigger(trig)
                    if self.printer.status().state == "paused":  # no operator at a virtual printer
                        self._pool.shutdown(wait=True)
                        break
                    if trig is None and self.printer.status().state in ("finished", "cancelled"):
                        break
                    continue
                try:
                    for trig in self.printer.poll_triggers():
                        self.handle_trigger(trig)
                    state = self.printer.status().state
                    backoff = self.initial_backoff_s
                    if outage is not None:
                        _log("printer_reconnected", after_s=round(time.monotonic() - outage[0], 1),
                             failed_polls=outage[1], state=state)
                        outage = None
                    if state in TRANSIENT_STATES:
                        # pausing/resuming/cancelling: neither paused nor resumed yet; prev_state keeps
                        # the last settled state, so "pausing -> printing" is no operator resume
                        if state != last_seen:
                            _log("transient", state=state)
                    else:
                        if prev_state == "paused" and state == "printing" and self.policy.halted:
                            _log("resumed", layer=self.report.results[-1].layer if self.report.results else None)
                            self.acknowledge()  # the operator resumed: accept what was seen
                        prev_state = state
                    last_seen = state
                except PrinterError as exc:
                    # never a pause: alert once per outage, then log each retry (capped exponential backoff)
                    _log("printer_unreachable", retry_s=backoff, error=str(exc))
                    if outage is None:
                        outage = (time.monotonic(), 0)
                        self._alert(f"printer unreachable, retrying with backoff up to {self.max_backoff_s:g} s: {exc}")
                    outage = (outage[0], outage[1] + 1)
                    self.stop_event.wait(backoff)
                    backoff = min(backoff * 2, self.max_backoff_s)
                    continue
                if state in ("finished", "cancelled", "idle") and self.report.results:
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

    def _outcome(self) -> str:
        try:
            state = self.printer.status().state
        except LayerwatchError:
            return "unknown"
        return {"finished": "done", "cancelled": "cancelled", "paused": "paused"}.get(
            state, "stopped" if self.stop_event.is_set() else state)
