"""The per-layer task a farm hands to its workers: one photo through the job's pipeline.

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
import threading
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from layerwatch.analysis.overlay import overlay_image
from layerwatch.analysis.result import BlockGrid, LayerResult
from layerwatch.errors import LayerwatchError
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.step import LayerPipeline, Reference

__all__ = ["JobContext", "Verdict", "analyse_on", "analyse_remote", "forget_pipeline", "MEMO", "PIPELINES_PER_WORKER",
           "THUMB_WIDTH", "WARP_MAPS"]

#: references a farm pipeline keeps in memory: the layer being judged (its thumbnail reuses it; dropped once the
#: layer is recorded, :meth:`LayerPipeline.forget_references`); memory per printer
MEMO = 1
#: per-height remap tables a farm pipeline keeps (about 2.5 MB each at 600 x 600 px): the layer being judged
#: (its scene-channel step reuses it). Each layer has its own height, so more would only fill up over the
#: first layers of every job (16 by default: ~40 MB per printer) without a hit.
WARP_MAPS = 1

#: pipelines a Dask worker process keeps (one per job it analyses)
PIPELINES_PER_WORKER = 1024
#: width of the overlay thumbnail, px
THUMB_WIDTH = 160

_pipelines: OrderedDict[str, LayerPipeline] = OrderedDict()
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
    """

    key: str
    toolpath: Toolpath
    camera: CameraModel
    config: JobConfig

    def pipeline(self) -> LayerPipeline:
        """A new pipeline for this job (:data:`MEMO` references, :data:`WARP_MAPS` remap tables kept)."""
        pipe = LayerPipeline(self.toolpath, self.camera, self.config, memo=MEMO)
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
    thumb : bytes or None
        PNG of the overlay (failing regions over the top view), :data:`THUMB_WIDTH` px wide.
    reference : Reference or None
        The reference the photo was compared with, when asked for (the image store writes it;
        sent back rather than rendered again where the verdict is used).
    """

    result: LayerResult
    top: np.ndarray | None = None
    thumb: bytes | None = None
    reference: Reference | None = None


def _thumbnail(pipe: LayerPipeline, top: np.ndarray, res: LayerResult) -> bytes | None:
    """PNG bytes of the overlay of ``res`` over ``top``, :data:`THUMB_WIDTH` px wide (``None`` if it cannot be drawn).

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
    drawn = res
    try:
        footprint = pipe.reference(res.layer).footprint
        if f > 1:  # the top view and footprint area-averaged to the small scale, the grid's cells to 2 px
            top = cv2.resize(top, (w // f, h // f), interpolation=cv2.INTER_AREA)
            footprint = cv2.resize(footprint.astype(np.uint8), (w // f, h // f), interpolation=cv2.INTER_AREA) > 0
            drawn = dataclasses.replace(res, grid=dataclasses.replace(grid, cell_px=2))
        rgb = overlay_image(top, drawn, small_tv, footprint, caption=False)
    except (LayerwatchError, ValueError) as exc:  # the record counts, the picture is a nicety
        res.message = res.message or f"no overlay: {exc}"
        return None
    h, w = rgb.shape[:2]
    small = cv2.resize(rgb, (THUMB_WIDTH, max(1, round(h * THUMB_WIDTH / w))), interpolation=cv2.INTER_AREA)
    ok, png = cv2.imencode(".png", cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
    return png.tobytes() if ok else None


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
    # the next layer has another height: its remap tables would only be held, never used; the distortion
    # lookup (2.2 MB at 1080p) is rebuilt in ~3 ms per layer rather than held by each of hundreds of printers.
    # With keep_lookup the caller (the monitor's lag check, here) uses both for this photo and drops them when
    # the layer is recorded (PoolPipeline.layer_done).
    if not keep_lookup:
        pipe.warper.clear(lookups=True)
    ref = pipe.reference(res.layer) if with_reference and top is not None else None  # memoised: no second render
    return Verdict(res, top, thumb, ref)


def _pipeline_for(ctx: JobContext) -> LayerPipeline:
    with _lock:
        pipe = _pipelines.get(ctx.key)
        if pipe is not None:
            _pipelines.move_to_end(ctx.key)
            return pipe
    pipe = ctx.pipeline()
    with _lock:
        pipe = _pipelines.setdefault(ctx.key, pipe)
        while len(_pipelines) > PIPELINES_PER_WORKER:
            _pipelines.popitem(last=False)
    return pipe


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
