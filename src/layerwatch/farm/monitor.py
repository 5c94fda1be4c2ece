"""The monitor of one farm printer: :class:`~layerwatch.monitor.service.Monitor` on the farm's pool.

:class:`FarmMonitor` is the monitor loop unchanged (triggers, camera, policy,
pause, alerts, history, operator resume and acknowledgements) through its
public hooks (the ``executor`` it analyses on, :meth:`Monitor.finish_layer`,
:meth:`Monitor.record_event`), with these differences:

* its analysis executor is a :class:`~layerwatch.farm.pool.FrameLane`: at most
  ``queue_frames`` photos wait; when the farm's workers fall behind, the
  oldest is dropped and a ``frame_dropped`` event records its layer;
* its pipeline is a :class:`PoolPipeline`: the per-layer compute runs on the
  farm's shared :class:`~layerwatch.farm.pool.WorkerPool` (threads or Dask);
* its camera-fault gate is the monitor's: the pipeline gives the monitor the job's
  camera model and settings (bed-marker check on every frame) and the top view and
  references of the layers (lag check where a result would count toward a pause),
  so a farm printer's frames are judged as ``layerwatch monitor`` judges them;
* on a Dask cluster the whole frame goes to the job's worker
  (:func:`~layerwatch.farm.remote.judge_remote`): the camera's JPEG bytes when it sends
  them (:meth:`~layerwatch.monitor.cameras.Camera.grab_encoded`; ~0.3 MB instead of the
  6 MB decoded frame), decoded there, with the stale-frame check, the camera-fault gate and
  marker check, the analysis and the lag check's analysis; the service only applies the
  verdict (policy, pause, alerts, history, images), so a camera fault is still an alert and
  never a pause, and the records are those of local threads;
* it keeps only the last :data:`RESULTS_KEPT` layer records in memory
  (:attr:`report`): the farm reads its layers from the history, and a printer's
  memory must not grow with the length of its prints;
* each photo is stamped with the monitor's *generation*; an operator
  acknowledge or resume, and the end of the job, start a new one. A verdict on
  a photo of an older generation (it arrived late) is recorded, with a
  ``late_verdict`` event, but never fed to the policy, so it can neither pause
  nor cancel: the operator has looked at the print since that photo, or the
  job it belongs to is over. The check and the pause request hold one lock,
  so a resume cannot slip between them.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from layerwatch.analysis.result import LayerResult
from layerwatch.errors import LayerwatchError
from layerwatch.farm.pool import FrameLane, WorkerPool
from layerwatch.farm.remote import (
    FrameRules,
    FrameVerdict,
    JobContext,
    Thumbnail,
    Verdict,
    analyse_on,
    analyse_remote,
    judge_remote,
)
from layerwatch.monitor.printers.base import SnapshotTrigger
from layerwatch.monitor.service import Monitor, MonitorReport, pipeline_error
from layerwatch.pipeline.step import LayerPipeline, Reference

__all__ = ["FarmMonitor", "PoolPipeline", "StampedTrigger", "RESULTS_KEPT"]

log = logging.getLogger("layerwatch.farm")

#: layer records (and decisions) a farm monitor keeps in memory; all of them are in the history database
RESULTS_KEPT = 8


@dataclass(frozen=True)
class StampedTrigger(SnapshotTrigger):
    """A snapshot trigger with the monitor generation it was taken in."""

    generation: int = 0


class PoolPipeline:
    """The pipeline a farm monitor calls: the compute goes to the shared pool.

    Parameters
    ----------
    pool : WorkerPool
    pipeline : LayerPipeline
        The job's pipeline here (runs the work on local threads; gives the
        top view and footprints for alert overlays in both modes).
    context : JobContext, optional
        The job for Dask workers (required when the pool is distributed).
    with_reference : bool
        Bring each analysed layer's reference back with its verdict (for an image store on a
        Dask pool: :meth:`reference` then renders nothing here).
    """

    def __init__(self, pool: WorkerPool, pipeline: LayerPipeline, context: JobContext | None = None, *,
                 with_reference: bool = False) -> None:
        self.pool, self.local = pool, pipeline
        self.with_reference = with_reference
        self._reference: tuple[int, Reference] | None = None  # the last verdict's (layer, reference)
        self._footprint: tuple[int, FrameVerdict] | None = None  # the last verdict's (layer, packed footprint)
        self.context = pool.scatter(context) if pool.distributed else None
        self.key = context.key if context is not None and self.context is not None else None  # the job's worker pin
        self.topview = pipeline.topview
        #: the job's posed camera and settings (the monitor's marker and lag checks read them)
        self.camera, self.config = pipeline.camera, pipeline.config
        self.last_top: np.ndarray | None = None
        self.last_thumb: Thumbnail | None = None

    def process(self, photo: np.ndarray, layer_index: int) -> LayerResult:
        """:meth:`LayerPipeline.process` on a pool worker (blocks this printer's lane, not the others)."""
        if self.context is not None:
            v: Verdict = self.pool.run(analyse_remote, self.context, photo, layer_index, self.with_reference,
                                       key=self.key)
        else:
            v = self.pool.run(analyse_on, self.local, photo, layer_index, self.with_reference, True)
        self.last_top, self.last_thumb = v.top, v.thumb
        self._reference = (v.result.layer, v.reference) if v.reference is not None else None
        return v.result

    @property
    def remote(self) -> bool:
        """The job's frames go to a Dask worker (:meth:`judge`)."""
        return self.context is not None

    def judge(self, frame: Any, layer: int, z: float, photo_ms: float, interrupted: bool,
              rules: FrameRules) -> FrameVerdict:
        """The whole frame on the job's Dask worker (:func:`~layerwatch.farm.remote.judge_remote`): decode, gate,
        analysis, thumbnail, lag check's analysis; blocks this printer's lane."""
        v: FrameVerdict = self.pool.run(judge_remote, self.context, frame, layer, z, photo_ms, interrupted, rules,
                                        self.with_reference, key=self.key)
        self.last_top, self.last_thumb = v.top, v.thumb
        self._reference = (v.result.layer, v.reference) if v.reference is not None else None
        self._footprint = (v.result.layer, v) if v.footprint is not None else None
        return v

    def alert_footprint(self, index: int) -> np.ndarray:
        """The top-view footprint of layer ``index`` (bool) for an alert's overlay: the last verdict's, else its
        reference's."""
        if self._footprint is not None and self._footprint[0] == index:
            foot = self._footprint[1].layer_footprint()
            if foot is not None:
                return foot
        return self.reference(index).footprint

    def reference(self, index: int) -> Reference:
        """The reference of layer ``index``: the one the last verdict brought, else rendered here (alert overlays)."""
        if self._reference is not None and self._reference[0] == index:
            return self._reference[1]
        return self.local.reference(index)

    def top_view(self, photo: np.ndarray, z: float,
                 box: tuple[slice, slice] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`LayerPipeline.top_view` here (the monitor's lag check: the photo on the previous layer's plane)."""
        return self.local.top_view(photo, z, box)  # tables and lookup are dropped when the layer is recorded

    def keep_top_view(self, photo: np.ndarray, z: float, box: tuple[slice, slice]) -> bool:
        """:meth:`LayerPipeline.keep_top_view` here (on local threads the analysis warped the photo here)."""
        return self.local.keep_top_view(photo, z, box)

    def layer_done(self) -> None:
        """The layer is recorded: drop its top view, reference, the warper's remap tables and distortion lookup
        (made again from its kept crop in ~0.2 ms, :meth:`TopViewWarper.clear`; a printer holds between layers
        the small box the lag check keeps, the lookup's crop and the last layer's reference image and footprint
        bits, which the next frame's lag check asks for: :meth:`LayerPipeline.reference`)."""
        self.last_top = self._reference = self._footprint = None
        self.local.forget_references()
        self.local.warper.clear(lookups=True)

    def close(self) -> None:
        """The job ended: free its Dask worker (pin and pipeline) and the last top view kept here."""
        if self.key is not None:
            self.pool.release(self.key)
        self.last_top = self.last_thumb = self._reference = self._footprint = None


class FarmMonitor(Monitor):
    """A :class:`Monitor` on a shared pool with a bounded lane and late-verdict guard (module notes).

    Parameters
    ----------
    *args, **kwargs
        As for :class:`Monitor` (``pipeline`` a :class:`PoolPipeline`); not ``wait_for_verdict``
        with a lane smaller than needed: a waiting printer has one frame at a time anyway.
    queue_frames : int
        Photos that may wait for a worker.
    observe : callable, optional
        ``observe(result, thumb)`` after each recorded layer (the farm's printer card; ``thumb`` a
        :class:`~layerwatch.farm.remote.Thumbnail`, drawn when asked for).
    """

    def __init__(self, *args: Any, queue_frames: int = 2,
                 observe: Callable[[LayerResult, Thumbnail | None], None] | None = None, **kwargs: Any) -> None:
        self._lane = FrameLane(queue_frames, on_drop=self._dropped, name="layerwatch-lane")
        super().__init__(*args, executor=self._lane, **kwargs)
        self.report = MonitorReport(results=deque(maxlen=RESULTS_KEPT),  # type: ignore[arg-type]
                                    decisions=deque(maxlen=RESULTS_KEPT))  # type: ignore[arg-type]
        self.generation = 0
        self.dropped = self.late = 0
        self.observe = observe
        self._generation_lock = threading.RLock()
        #: the frames go to the job's Dask worker whole (:meth:`PoolPipeline.judge`)
        self.remote = bool(getattr(self.pipeline, "remote", False))
        self._interrupted = False  # a camera fault since the last frame sent (the worker's late stream hears of it)

    def _grab(self) -> Any:
        """The frame as the camera sent it when it goes to a Dask worker (decoded there), else decoded here."""
        if self.remote and getattr(self.camera, "encoded", False):
            return self.camera.grab_encoded()
        return self.camera.grab()

    def _analyse(self, trigger: SnapshotTrigger, photo: Any, t_photo: float) -> LayerResult:
        """:meth:`Monitor._analyse`; on a Dask cluster the frame's checks and analysis run on the job's worker and
        only the verdict is applied here (module notes)."""
        if not self.remote:
            return super()._analyse(trigger, photo, t_photo)
        photo_ms = round((t_photo - trigger.time) * 1000, 1)
        rules = FrameRules(self.frame_quality, self.faults.camera_alert_after, self.policy.settings)
        try:
            pipe: Any = self.pipeline  # a PoolPipeline, possibly inside a StoringPipeline
            v = pipe.judge(photo, trigger.layer, trigger.z, photo_ms, self._interrupted, rules)
        except Exception as exc:  # noqa: BLE001 - a lost worker or a pipeline bug must not stop the monitor
            res = pipeline_error(trigger.layer, trigger.z, exc, log)
            res.photo_ms = photo_ms
            return self.finish_layer(trigger, res)
        self._interrupted = False
        res = v.result
        if v.gated:
            return self.finish_layer(trigger, res)
        store = getattr(self.pipeline, "store_layer", None)  # a StoringPipeline around the PoolPipeline
        if store is not None:
            res = store(res)
        res = self.judge_late(res, v.late, v.late_count)
        top = getattr(self.pipeline, "last_top", None) if res.status == "ok" else None
        return self.finish_layer(trigger, res, top)

    def _footprint(self, layer: int) -> np.ndarray:
        """:meth:`Monitor._footprint`: on a Dask cluster the verdict brought it (no reference rendered here)."""
        foot = getattr(self.pipeline, "alert_footprint", None)  # a PoolPipeline, possibly inside a StoringPipeline
        return foot(layer) if foot is not None else super()._footprint(layer)

    def _stream_interrupted(self) -> None:
        """:meth:`Monitor._stream_interrupted`, and the job's worker hears of it with the next frame."""
        super()._stream_interrupted()
        self._interrupted = True

    def handle_trigger(self, trigger: SnapshotTrigger) -> LayerResult | None:
        """Stamp the trigger with the current generation, then take and queue the photo."""
        stamped = StampedTrigger(trigger.layer, trigger.z, trigger.source, trigger.time, trigger.signal,
                                 generation=self.generation)
        return super().handle_trigger(stamped)

    def new_generation(self, why: str) -> None:
        """Photos taken before now can no longer pause (an operator action, or the job ended)."""
        with self._generation_lock:
            self.generation += 1
        log.info("generation %d (%s)", self.generation, why)

    def acknowledge(self, source: str = "resume") -> None:
        """The operator accepted the print as it is: a new generation, then the policy's acknowledge."""
        self.new_generation(f"acknowledged ({source})")
        super().acknowledge(source)

    def _dropped(self, args: tuple) -> None:
        """A pending photo was dropped from the full lane (``args``: the analysis call's arguments)."""
        trigger = args[0]
        self.dropped += 1
        self.record_event("frame_dropped", f"layer {trigger.layer} not analysed: the workers are saturated "
                    f"(the {self._lane.capacity} newest photos are kept)", {"layer": trigger.layer})

    def finish_layer(self, trigger: SnapshotTrigger, res: LayerResult, top: np.ndarray | None = None) -> LayerResult:
        """:meth:`Monitor.finish_layer` for a photo of the current generation; a late one is only recorded."""
        with self._generation_lock:
            gen = getattr(trigger, "generation", self.generation)
            if gen == self.generation:
                out = super().finish_layer(trigger, res, top)
            else:
                out = self._late(trigger, res)
        if self.observe is not None:
            self.observe(out, getattr(self.pipeline, "last_thumb", None) if out.status == "ok" else None)
        done = getattr(self.pipeline, "layer_done", None)  # a PoolPipeline, possibly inside a StoringPipeline
        if done is not None:
            done()
        return out

    def _late(self, trigger: SnapshotTrigger, res: LayerResult) -> LayerResult:
        """Record a verdict of an older generation without acting on it."""
        self.late += 1
        res.decision, res.decision_reason = "none", (
            f"late verdict on layer {trigger.layer}: the operator acted or the job ended since the photo; not acted on")
        self.report.results.append(res)
        if self.history is not None and self.job_id is not None:
            try:
                self.history.add_layer(self.job_id, res)
            except LayerwatchError as exc:
                log.warning("history write failed: %s", exc)
        self.record_event("late_verdict", res.decision_reason, {"layer": trigger.layer})
        return res
