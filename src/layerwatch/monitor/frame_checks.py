"""A job's camera-fault checks on each frame, with their state: the gate, the bed markers, the late stream.

:class:`FrameChecks` is the part of a frame's judgement that needs only the frame, the job's
pipeline and what the checks remember of the earlier frames (the previous usable frame,
reduced; where the bed markers were; the late-stream series). The monitor runs it on its
analysis thread; a farm on a Dask cluster runs it on the worker that holds the job's pipeline
(:mod:`layerwatch.farm.remote`), beside the analysis, so the service never decodes a photo.
What acts on the printer or the operator (records, alerts, pauses) stays with the monitor:
:meth:`FrameChecks.late` only *computes* the lag verdict (:class:`~layerwatch.monitor.camera_checks.LateCheck`),
and the monitor applies it.

The checks' state is the job's: a worker that starts a job's frames afresh (the worker before
left) starts it empty, as a monitor does at the job's start.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from layerwatch.analysis.frame_quality import (
    FrameQualitySettings,
    assess_frame,
    compact_previous,
    grey_of,
    marker_offset_px,
    marker_search_px,
)
from layerwatch.analysis.result import LayerResult
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.roi import bed_roi
from layerwatch.geometry.topview import TopView
from layerwatch.monitor.camera_checks import LateCheck, LateStream, MarkerWatch, lag_checkable
from layerwatch.monitor.printers.replies import RateLimitedLog
from layerwatch.pipeline.checks import print_reach_mm, print_top_z_mm
from layerwatch.pipeline.policy import PolicySettings

__all__ = ["CAMERA_FAULT", "FrameChecks"]

#: ``LayerResult.status`` of a layer whose photo was unusable (the policy does not judge it)
CAMERA_FAULT = "camera_fault"

log = logging.getLogger("layerwatch.monitor")

#: a region of interest that covers at least this share of the frame is not used (the whole frame is judged)
ROI_MOST = 0.9


def _roi_source(pipeline: Any) -> tuple[CameraModel, TopView, float, tuple[float, float, float, float] | None] | None:
    """The posed camera, observed square, print's top (mm) and reach (bed mm) of a job's pipeline, or None when one
    of the first three is missing.

    ``pipeline``: a :class:`~layerwatch.pipeline.step.LayerPipeline`, or a farm's pool pipeline (its ``local`` one),
    possibly inside an image store's wrapper.
    """
    cam, topview = getattr(pipeline, "camera", None), getattr(pipeline, "topview", None)
    toolpath = getattr(pipeline, "toolpath", None)
    if toolpath is None:
        toolpath = getattr(getattr(pipeline, "local", None), "toolpath", None)
    if not isinstance(cam, CameraModel) or not cam.has_pose or not isinstance(topview, TopView) or toolpath is None:
        return None
    top = print_top_z_mm(toolpath)
    return (cam, topview, top, print_reach_mm(toolpath)) if top is not None and np.isfinite(top) else None


def _markers_sink(pipeline: Any) -> Any:
    """The job's ``LayerPipeline.markers_moved``: on ``pipeline``, through an image store's wrapper, or on a farm's
    pool pipeline's ``local`` one; None when there is none (another pipeline)."""
    for p in (pipeline, getattr(pipeline, "local", None)):
        sink = getattr(p, "markers_moved", None)
        if callable(sink):
            return sink
    return None


class FrameChecks:
    """The camera-fault gate, bed-marker watch and late-stream series of one job.

    Parameters
    ----------
    pipeline : object
        The job's pipeline (``camera`` and ``config`` for the marker watch; ``reference``,
        ``top_view``, ``topview`` and ``config`` for the lag check).
    frame_quality : FrameQualitySettings, optional
        The gate's settings; ``None`` or disabled: no gate, no marker or lag check.
    after_n : int
        Excused late frames in a row before the lag is alerted (:class:`LateStream`).
    warn : RateLimitedLog, optional
        Where a marker detection that failed is warned about (rate limited).
    """

    def __init__(self, pipeline: Any, frame_quality: FrameQualitySettings | None, after_n: int,
                 warn: RateLimitedLog | None = None) -> None:
        self.frame_quality = frame_quality if frame_quality is not None and frame_quality.enabled else None
        self.warn = warn or RateLimitedLog(log, 60.0)
        #: the last frame the gate passed, reduced (:func:`compact_previous`; not the frame: a farm holds one per printer)
        self.last_good: np.ndarray | None = None
        self.markers = (MarkerWatch.of_pipeline(pipeline, self.frame_quality.max_marker_shift_px)
                        if self.frame_quality is not None else None)
        self.late_stream = LateStream(after_n)
        self.lag_checks = self.frame_quality is not None and lag_checkable(pipeline)
        #: what the region of interest is computed from (camera, observed square, print's top and reach), None: the
        #: whole frame
        self._roi_of = _roi_source(pipeline) if self.frame_quality is not None and self.frame_quality.roi else None
        self._roi: dict[tuple[int, int], tuple[slice, slice] | None] = {}
        #: the job's :meth:`LayerPipeline.markers_moved <layerwatch.pipeline.step.LayerPipeline.markers_moved>`, told
        #: where the markers of each frame the gate passes lie (None: no markers, or a pipeline without it)
        self._markers_to = _markers_sink(pipeline) if self.markers is not None else None

    def gate(self, layer: int, z: float, photo: np.ndarray) -> LayerResult | None:
        """The camera-fault gate: a ``camera_fault`` record for a frame unfit for analysis, else None.

        ``photo``: BGR uint8, shape (h, w, 3). A frame that passes becomes the next one's "previous".
        """
        if self.frame_quality is None:
            return None
        try:
            grey = grey_of(photo)  # converted once: the gate's checks, the markers and the next frame's "previous"
            box = self.roi(grey.shape)
            small = compact_previous(grey)  # reduced once: the gate's and, if it passes, the next frame's previous
            markers = self.marker_positions(grey)
            quality = assess_frame(grey, self.last_good, self.frame_quality, small=small, box=box, **markers)
        except Exception:  # noqa: BLE001 - a gate bug must not blind the monitor: analyse the frame
            log.exception("frame-quality gate failed on layer %d; the frame is analysed unchecked", layer)
            return None
        if quality.ok:
            self.last_good = small
            if self._markers_to is not None:  # where the camera's image is: the analysis' view shift starts from it
                self._markers_to(marker_offset_px(markers["markers_px"], markers["expected_markers_px"],
                                                  marker_search_px(grey.shape)) if markers else None,
                                 (int(grey.shape[1]), int(grey.shape[0])))
            return None
        res = LayerResult(layer=layer, z=z, status=CAMERA_FAULT, message="unusable frame: " + "; ".join(quality.reasons))
        res.frame_quality = {k: round(float(v), 3) for k, v in quality.figures.items()}
        return res

    def roi(self, shape: tuple[int, ...]) -> tuple[slice, slice] | None:
        """The gate's region of interest in frames of ``shape`` (:func:`~layerwatch.geometry.roi.bed_roi`, computed once
        per frame size), or None: the whole frame (``[frame_quality] roi`` off, no posed camera, or a box that is
        most of the frame anyway)."""
        if self._roi_of is None:
            return None
        key = (int(shape[1]), int(shape[0]))
        if key not in self._roi:
            camera, topview, top_z, reach = self._roi_of
            try:
                extra = self.markers.expected_px(key) if self.markers is not None else None
                box = bed_roi(camera, topview, top_z, key, extra, reach)
            except Exception as exc:  # noqa: BLE001 - no region of interest rather than no gate
                self.warn.warning("roi", "camera-fault gate on the whole frame: %s: %s", type(exc).__name__, exc)
                box = None
            if box is not None:
                area = (box[0].stop - box[0].start) * (box[1].stop - box[1].start)
                box = box if area < ROI_MOST * key[0] * key[1] else None
            self._roi[key] = box
        return self._roi[key]

    def marker_positions(self, photo: np.ndarray) -> dict[str, np.ndarray]:
        """Detected and expected bed markers for the gate (empty without a marker calibration); ``photo`` BGR or grey."""
        if self.markers is None:
            return {}
        try:
            return self.markers(photo)
        except Exception as exc:  # noqa: BLE001 - no marker verdict rather than no gate
            self.warn.warning("markers", "bed markers not checked on this frame: %s: %s", type(exc).__name__, exc)
            return {}

    def late(self, pipeline: Any, photo: np.ndarray, res: LayerResult, policy: PolicySettings) -> LateCheck | None:
        """The late-stream check of an analysed frame (:meth:`LateStream.check`), or None when it does not run
        (no gate, a pipeline that cannot be asked, a result that is not ``ok``) or failed (logged: the layer is
        then judged as analysed). ``res`` is not changed."""
        if not self.lag_checks or res.status != "ok":
            return None
        try:
            excuse = bool(self.frame_quality and self.frame_quality.excuse_late_frames)
            return self.late_stream.check(pipeline, photo, res, policy, excuse=excuse)
        except Exception:  # noqa: BLE001 - a check bug must not hide the layer: judge it as analysed
            log.exception("lag check failed on layer %d; the layer is judged as analysed", res.layer)
            return None
