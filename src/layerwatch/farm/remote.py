"""The per-layer task a farm hands to its workers: one photo through the job's pipeline.

On a Dask cluster the task is :func:`judge_remote`: the frame as the camera sent it (an
:class:`~layerwatch.monitor.cameras.EncodedFrame`, ~0.3 MB for a 1080p JPEG; a simulated camera's
array as it is) goes to the worker that holds the job, which decodes it (and checks for a
repeated frame), runs the camera-fault gate and the bed-marker check
(:class:`~layerwatch.monitor.frame_checks.FrameChecks`), the per-layer step, the thumbnail and the
lag check's analysis, and returns a :class:`FrameVerdict`: the record, what the lag check found,
the top view and thumbnail. The gate's state (the previous usable frame, where the markers were,
the late-stream series, the last frame's fingerprint) lives with the job's pipeline on that
worker (:class:`WorkerJob`); a worker that takes over a job whose worker left starts it afresh, as
the pipeline does. The service keeps everything that acts (the policy, pauses, alerts, the
history): a camera fault the service itself saw (no frame) reaches the worker's late-stream series
with the job's next frame (``interrupted``), as it reaches the monitor's before its next frame.
One difference from a camera that decodes: a frame dropped from a saturated printer's lane never
reaches the worker, so the stale-frame check compares the next frame with the last one analysed,
not the last one taken (a stream frozen at a dropped frame is told one frame later, and the gate's
repeated-frame check sees it too).

:func:`analyse_on` runs :meth:`LayerPipeline.process <layerwatch.pipeline.step.LayerPipeline.process>`
(reference rendering, warp, analysis: the one per-layer step) and draws the
small overlay thumbnail the farm dashboard shows. On local threads the
printer's own pipeline is passed; on a Dask cluster :func:`analyse_remote`
receives a :class:`JobContext` (scattered once per job) and keeps one
pipeline per job in each worker process (dropped by :func:`forget_pipeline` when
the job ends; at most :data:`PIPELINES_PER_WORKER`, least recently used dropped),
so references stay incremental and memoised there.
The records are the same either way: the same code runs on the same inputs.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from layerwatch.analysis.overlay import overlay_image
from layerwatch.analysis.result import BlockGrid, LayerResult
from layerwatch.errors import LayerwatchError
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.monitor.camera_checks import LateCheck
from layerwatch.monitor.cameras import EncodedFrame, StaleCheck
from layerwatch.monitor.frame_checks import CAMERA_FAULT, FrameChecks
from layerwatch.monitor.service import camera_error, frame_problem, pipeline_error
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.job_geometry import PrinterGeometries
from layerwatch.pipeline.policy import PolicySettings
from layerwatch.pipeline.shared_references import SharedReferences
from layerwatch.pipeline.step import LayerPipeline, Reference

__all__ = ["GEOMETRY", "SHARED_REFERENCES", "FrameRules", "FrameVerdict", "JobContext", "Verdict", "WorkerJob", "analyse_on", "analyse_remote",
           "forget_pipeline", "judge_on", "judge_remote", "MEMO", "PIPELINES_PER_WORKER", "THUMB_WIDTH", "Thumbnail", "WARP_MAPS"]

log = logging.getLogger("layerwatch.farm")

#: references a farm pipeline keeps in memory: the layer being judged (its thumbnail reuses it; dropped once the
#: layer is recorded, :meth:`LayerPipeline.forget_references`); memory per printer
MEMO = 1
#: per-height remap tables a farm pipeline keeps (about 2.5 MB each at 600 x 600 px): the layer being judged
#: (its scene-channel step reuses it). Each layer has its own height, so more would only fill up over the
#: first layers of every job (16 by default: ~40 MB per printer) without a hit.
WARP_MAPS = 1

#: the references the farm pipelines of this process share (:mod:`layerwatch.pipeline.shared_references`: printers
#: printing the same file with the same camera model render each layer once; each Dask worker process has its own),
#: at most 256 MB (~230 references at 600 x 600 px)
SHARED_REFERENCES = SharedReferences(max_mb=256.0)

#: the job geometry of each printer whose jobs this process builds (:mod:`layerwatch.pipeline.job_geometry`: a
#: printer's next job with the same file and camera takes its view maps, ~60 ms of a job start with the example
#: camera; each Dask worker process has its own). A printer's entries are the arrays its current job holds.
GEOMETRY = PrinterGeometries(max_printers=1024)

#: pipelines a Dask worker process keeps (one per job it analyses)
PIPELINES_PER_WORKER = 1024
#: width of the overlay thumbnail, px
THUMB_WIDTH = 160

_pipelines: OrderedDict[str, WorkerJob] = OrderedDict()
_lock = threading.Lock()


@dataclass(frozen=True)
class JobContext:
    """What a worker needs to build a job's pipeline.

    Attributes
    ----------
    key : str
        Unique per job (printer name and job id); names the worker's pipeline.
    toolpath : Toolpath
    camera : CameraModel
        With its bed pose.
    config : JobConfig
    share_references : bool
        The job's pipelines read and store their references in the process's :data:`SHARED_REFERENCES`
        (the farm service's jobs do; records are the same either way).
    printer : str or None
        The printer whose job it is: its job geometry (:data:`GEOMETRY`) is kept for its next job
        (``None``: nothing kept; records are the same either way).
    """

    key: str
    toolpath: Toolpath
    camera: CameraModel
    config: JobConfig
    share_references: bool = False
    printer: str | None = None

    def pipeline(self) -> LayerPipeline:
        """A new pipeline for this job (:data:`MEMO` references, :data:`WARP_MAPS` remap tables kept; the process's
        shared references with :attr:`share_references`; the printer's :data:`GEOMETRY` with :attr:`printer`)."""
        pipe = LayerPipeline(self.toolpath, self.camera, self.config, memo=MEMO,
                             shared=SHARED_REFERENCES if self.share_references else None,
                             geometry=None if self.printer is None else GEOMETRY.of(self.printer))
        pipe.warper.cache_size = WARP_MAPS
        return pipe


@dataclass
class Verdict:
    """A worker's answer for one photo.

    Attributes
    ----------
    result : LayerResult
        The pipeline's record.
    top : ndarray, shape (H, W), uint8, or None
        Grey top view of an analysed photo (for alert overlays).
    thumb : Thumbnail or None
        The overlay (failing regions over the top view), :data:`THUMB_WIDTH` px wide, drawn when asked for.
    reference : Reference or None
        The reference the photo was compared with, when asked for (the image store writes it;
        sent back rather than rendered again where the verdict is used).
    """

    result: LayerResult
    top: np.ndarray | None = None
    thumb: Thumbnail | None = None
    reference: Reference | None = None


class Thumbnail:
    """The overlay thumbnail of one analysed layer (failing regions over the top view, :data:`THUMB_WIDTH` px wide),
    drawn and PNG-encoded the first time it is asked for (:meth:`png`), not on every frame: a farm draws hundreds of
    layers a minute, and a card's picture is looked at only while someone has the farm page open.

    It holds the top view and footprint already reduced to the drawing scale (~45 kB at 600 x 600 px) and the
    record as it was analysed (a shallow copy: the drawing reads its heatmap, grid and regions); the PNG is the
    one the eager drawing made, byte for byte.
    """

    def __init__(self, top: np.ndarray, footprint: np.ndarray, drawn: LayerResult, topview: TopView) -> None:
        self.top, self.footprint, self.drawn, self.topview = top, footprint, drawn, topview
        self._png: bytes | None = None
        self._failed = False

    def png(self) -> bytes | None:
        """PNG bytes (``None`` when the overlay cannot be drawn: logged once, the record is not changed)."""
        if self._png is None and not self._failed:
            try:
                rgb = overlay_image(self.top, self.drawn, self.topview, self.footprint, caption=False)
                h, w = rgb.shape[:2]
                small = cv2.resize(rgb, (THUMB_WIDTH, max(1, round(h * THUMB_WIDTH / w))),
                                   interpolation=cv2.INTER_AREA)
                ok, png = cv2.imencode(".png", cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
            except (LayerwatchError, ValueError) as exc:  # the record counts, the picture is a nicety
                log.warning("no overlay thumbnail for layer %d: %s", self.drawn.layer, exc)
                ok, png = False, None
            if ok and png is not None:
                self._png = png.tobytes()
            else:
                self._failed = True
        return self._png


def _thumbnail(pipe: LayerPipeline, top: np.ndarray, res: LayerResult) -> Thumbnail | None:
    """The overlay thumbnail of ``res`` over ``top`` (:class:`Thumbnail`: drawn when asked for; ``None`` if it cannot
    be drawn).

    Drawn at the scale where a HOG cell is 2 px (a quarter of the default top view: the
    heatmap's blocks land on whole pixels, the outlines stay one pixel wide), not at full size
    and then shrunk: the card shows ~160 px. No caption: the card writes layer and a% itself.
    """
    grid = res.grid or BlockGrid()
    f = grid.cell_px // 2 if grid.cell_px % 2 == 0 else 1
    tv = pipe.topview
    small_tv = TopView(tv.px_per_mm / f, tv.width_mm, tv.height_mm, tv.center_mm) if f > 1 else tv
    h, w = tv.shape
    if small_tv.shape != (h // f, w // f) or h % f or w % f:
        f, small_tv = 1, tv
    drawn = dataclasses.replace(res)  # the record as analysed (the monitor goes on to fill in its decision)
    try:
        footprint = pipe.reference(res.layer).footprint
        if f > 1:  # the top view and footprint area-averaged to the small scale, the grid's cells to 2 px
            top = cv2.resize(top, (w // f, h // f), interpolation=cv2.INTER_AREA)
            footprint = cv2.resize(footprint.astype(np.uint8), (w // f, h // f), interpolation=cv2.INTER_AREA) > 0
            drawn = dataclasses.replace(res, grid=dataclasses.replace(grid, cell_px=2))
    except (LayerwatchError, ValueError) as exc:  # the record counts, the picture is a nicety
        res.message = res.message or f"no overlay: {exc}"
        return None
    return Thumbnail(top, footprint, drawn, small_tv)


def analyse_on(pipe: LayerPipeline, photo: np.ndarray, layer: int, with_reference: bool = False,
               keep_lookup: bool = False) -> Verdict:
    """The per-layer step on ``pipe`` and the overlay thumbnail of its result.

    Parameters
    ----------
    pipe : LayerPipeline
        The job's pipeline (one caller at a time).
    photo : ndarray, uint8, shape (h, w, 3)
        Camera frame, BGR.
    layer : int
        0-based layer index.
    with_reference : bool
        Return the reference of an analysed layer too (:attr:`Verdict.reference`).
    keep_lookup : bool
        Keep the warper's distortion lookup and this plane's remap tables: the caller warps this photo
        again (the monitor's lag check on local threads) and drops them when the layer is recorded.
    """
    res = pipe.process(photo, layer)
    top = pipe.last_top if res.status == "ok" else None
    thumb = _thumbnail(pipe, top, res) if top is not None and res.heatmap is not None else None
    pipe.last_top = pipe.last_valid = None  # the verdict carries the top view; a farm keeps hundreds of pipelines
    # the next layer has another height: its remap tables would only be held, never used; of the distortion
    # lookup (2.3 MB at 1080p) only the crop the planes' warps read is held (~0.5 MB), the rest made again.
    # With keep_lookup the caller (the monitor's lag check, here) uses both for this photo and drops them when
    # the layer is recorded (PoolPipeline.layer_done).
    if not keep_lookup:
        pipe.warper.clear(lookups=True)
    ref = pipe.reference(res.layer) if with_reference and top is not None else None  # memoised: no second render
    return Verdict(res, top, thumb, ref)


@dataclass(frozen=True)
class FrameRules:
    """The monitor's settings a worker's frame checks read (sent with each frame: the policy's are the monitor's
    at that moment).

    Attributes
    ----------
    frame_quality : FrameQualitySettings or None
        The camera-fault gate's (``None``: no gate, no marker or lag check).
    after_n : int
        Excused late frames in a row before the lag is alerted.
    policy : PolicySettings
        The pause policy's (which results count toward a pause: the lag check runs on those).
    """

    frame_quality: Any
    after_n: int
    policy: PolicySettings


class WorkerJob:
    """What a worker process holds for one job: its pipeline and, once its first frame is judged, its frame
    checks and the stale-frame fingerprint (module notes)."""

    def __init__(self, ctx: JobContext) -> None:
        self.pipeline = ctx.pipeline()
        self.checks: FrameChecks | None = None
        self.stale = StaleCheck()

    def frame_checks(self, rules: FrameRules) -> FrameChecks:
        """The job's :class:`FrameChecks` (made with the first frame's ``rules``)."""
        if self.checks is None:
            self.checks = FrameChecks(self.pipeline, rules.frame_quality, rules.after_n)
        return self.checks


@dataclass
class FrameVerdict:
    """A worker's answer for one frame (:func:`judge_on`).

    Attributes
    ----------
    result : LayerResult
        The frame's record before the lag check acts: a ``camera_fault`` (``gated``), or the
        pipeline's result (``photo_ms`` set).
    gated : bool
        The frame never reached the pipeline (not decodable, a repeated frame, refused by the gate).
    top, thumb, reference
        As :class:`Verdict`.
    late : LateCheck or None
        The lag check's outcome (its ``judged`` record, ``why``, ``alert``; without the figures the
        service does not read), for :meth:`Monitor.judge_late <layerwatch.monitor.service.Monitor.judge_late>`.
    late_count : int
        Excused late frames in a row on the worker (the alert's figure).
    footprint : ndarray, uint8, or None
        The analysed layer's top-view footprint, bit-packed (``np.packbits``, ~45 kB at 600 x 600 px): an
        alert's overlay on the service needs it, which would otherwise render the reference there
        (:meth:`layer_footprint` unpacks it).
    """

    result: LayerResult
    gated: bool = False
    top: np.ndarray | None = None
    thumb: Thumbnail | None = None
    reference: Reference | None = None
    late: LateCheck | None = None
    late_count: int = 0
    footprint: np.ndarray | None = None

    def layer_footprint(self) -> np.ndarray | None:
        """The analysed layer's top-view footprint (bool, the top view's shape), or None."""
        if self.footprint is None or self.top is None:
            return None
        h, w = self.top.shape[:2]
        return np.unpackbits(self.footprint, count=h * w).reshape(h, w).astype(bool)


def judge_on(job: WorkerJob, frame: EncodedFrame | np.ndarray, layer: int, z: float, photo_ms: float,
             interrupted: bool, rules: FrameRules, with_reference: bool = False) -> FrameVerdict:
    """One frame of ``job`` as the monitor's analysis thread judges it, up to what acts (module notes).

    Parameters
    ----------
    job : WorkerJob
    frame : EncodedFrame or ndarray
        The camera's bytes (decoded here, with the stale-frame check when the camera has it) or a
        BGR uint8 frame, shape (h, w, 3).
    layer : int
        0-based layer index of the trigger.
    z : float
        The trigger's height, mm.
    photo_ms : float
        Trigger to photo, ms (the record's ``photo_ms``).
    interrupted : bool
        The monitor recorded a camera fault since the job's previous frame (the late stream may slip there).
    rules : FrameRules
    with_reference : bool
        Return the reference of an analysed layer too.
    """
    checks = job.frame_checks(rules)
    if interrupted:
        checks.late_stream.interrupted()
    if isinstance(frame, EncodedFrame):
        try:
            photo = frame.decode(job.stale)
            problem = frame_problem(photo)
        except Exception as exc:  # noqa: BLE001 - any camera failure is a camera fault, never a crash
            problem = camera_error(exc)
        if problem is not None:
            return FrameVerdict(LayerResult(layer=layer, z=z, status=CAMERA_FAULT, message=problem), gated=True)
    else:
        photo = frame
    gated = checks.gate(layer, z, photo)
    if gated is not None:
        return FrameVerdict(gated, gated=True)
    pipe = job.pipeline
    try:
        v = analyse_on(pipe, photo, layer, with_reference, keep_lookup=True)
    except Exception as exc:  # noqa: BLE001 - a pipeline bug must not stop the monitor
        res = pipeline_error(layer, z, exc, log)
        res.photo_ms = photo_ms
        pipe.warper.clear(lookups=True)
        pipe.forget_references()
        return FrameVerdict(res)
    res = v.result
    res.photo_ms = photo_ms
    foot = np.packbits(pipe.reference(layer).footprint) if v.top is not None else None  # memoised: no render
    pipe.last_top = v.top  # the lag check reads the analysed top view (the monitor's pipeline gives it)
    try:
        late = checks.late(pipe, photo, res, rules.policy)
    finally:  # the layer is done here: as PoolPipeline.layer_done on local threads
        pipe.last_top = None
        pipe.warper.clear(lookups=True)
        pipe.forget_references()
    if late is not None:
        late = dataclasses.replace(late, progress=None, verdict=None)
    return FrameVerdict(res, False, v.top, v.thumb, v.reference, late, checks.late_stream.count, foot)


def _job_for(ctx: JobContext) -> WorkerJob:
    with _lock:
        job = _pipelines.get(ctx.key)
        if job is not None:
            _pipelines.move_to_end(ctx.key)
            return job
    job = WorkerJob(ctx)
    with _lock:
        job = _pipelines.setdefault(ctx.key, job)
        while len(_pipelines) > PIPELINES_PER_WORKER:
            _pipelines.popitem(last=False)
    return job


def _pipeline_for(ctx: JobContext) -> LayerPipeline:
    return _job_for(ctx).pipeline


def judge_remote(ctx: JobContext, frame: EncodedFrame | np.ndarray, layer: int, z: float, photo_ms: float,
                 interrupted: bool, rules: FrameRules, with_reference: bool = False) -> FrameVerdict:
    """:func:`judge_on` with the worker process's :class:`WorkerJob` of ``ctx``'s job (a Dask task)."""
    return judge_on(_job_for(ctx), frame, layer, z, photo_ms, interrupted, rules, with_reference)


def analyse_remote(ctx: JobContext, photo: np.ndarray, layer: int, with_reference: bool = False) -> Verdict:
    """:func:`analyse_on` with the worker process's pipeline of ``ctx``'s job (a Dask task).

    The layer's reference is not kept there after it (the verdict brings it when asked for;
    the monitor's own uses of references render them in the service).
    """
    pipe = _pipeline_for(ctx)
    verdict = analyse_on(pipe, photo, layer, with_reference)
    pipe.forget_references()
    return verdict


def forget_pipeline(key: str) -> bool:
    """Drop job ``key``'s pipeline from this worker process (the job ended); ``True`` if it was there."""
    with _lock:
        return _pipelines.pop(key, None) is not None
