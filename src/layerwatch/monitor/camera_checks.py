"""Camera-fault checks that need the job: a stream one layer late, and a camera that moved.

The camera-fault gate (:func:`~layerwatch.analysis.frame_quality.assess_frame`)
judges a frame by itself and against the previous one. Two camera faults need
what only the monitor's job knows, the layers' references and the calibration:

**A lagging stream** (:func:`previous_layer_explains`). A camera (or a
snapshot URL behind a cache or a slow encoder) that stays one layer late for
good delivers, at layer ``k``, a new picture of layer ``k - 1``: each frame
differs from the one before by a layer's progress, so the gate's repeat check
does not see it, and where layer ``k`` differs from layer ``k - 1`` (a new
feature, a top surface, the end of a part) the picture is "wrong" against
layer ``k``'s reference and would pause a good print. The check is made only
where it matters, on a layer whose analysis would count toward a pause
(:func:`counts_toward_pause`): the same photo is analysed once more against
layer ``k - 1``'s reference (warped at that layer's height). When the
previous layer explains the picture (its anomalous area is at most
:data:`LAG_EXPLAINED_SHARE` of the area against layer ``k``, or both are
below the policy's ``min_area_mm2``; not "below ``min_area_mm2``" alone, as
a part on which the analysis sees a few blocks of clean-print noise keeps
them against either layer; and the scene channel's change beside the print,
if it counts, lies where layer ``k - 1`` was printed and layer ``k`` is
not: a first layer's skirt or brim seen one layer late), the frame *looks* one
layer late. From that one photo a late camera cannot be told from a layer that
added nothing (a clog, a part torn off into spaghetti): both look like the
previous layer. :class:`LateStream` tells them apart over the series
(:meth:`LateStream.check`): a late camera still shows *progress* between
consecutive frames where the G-code printed (:func:`progress_between`), and it
fell behind at some frame that showed none (a repeat, or a new exposure of the
same layer); a stalled print shows no progress frame after frame, and an on-time
camera never slips. Only a frame the series calls late is *excused*: the
monitor judges the analysis against the layer the frame shows (layer ``k - 1``)
instead, records it with the layer (its reason in the message, the areas and
the progress in ``frame_quality``) and lets the scene channel take the frame's
change beside the print as the scene, as when the operator acknowledges it,
so that it does not count on the next layers. Any other frame is judged as it
is, its message saying why. The lag itself never counts toward a pause, yet a
late camera still watches the print: a failure in a late frame is anomalous
against the layer it shows and pauses as on time. A real failure is not
explained by the layer below: spaghetti, a foreign body, a shifted or detached
part and a missing patch are as anomalous against layer ``k - 1`` as against
layer ``k`` (the patch is a pit in both). After ``after_n`` excused frames with
no frame between them that its own layer explained better, the monitor alerts
once, as a camera fault ("camera lagging"). No timestamps are used: the
cameras layerwatch reads (MJPEG/snapshot URLs, Moonraker webcams) give none
that can be trusted against the printer's trigger.

**A camera that moved** (:class:`~layerwatch.monitor.marker_watch.MarkerWatch`,
re-exported here): each frame's bed markers against the calibration's projection.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from layerwatch.analysis.extrusion import block_ncc, highpass
from layerwatch.analysis.result import LayerResult
from layerwatch.analysis.scoring import analyze_layer
from layerwatch.monitor.marker_watch import MarkerWatch
from layerwatch.pipeline.policy import PolicySettings

__all__ = ["LAG_EXPLAINED_SHARE", "STILL_SHARE", "PRINTED_SHARE", "LagVerdict", "LateCheck", "LateStream", "MarkerWatch", "Progress",
           "counts_toward_pause", "lag_checkable", "previous_layer_explains", "progress_between"]

log = logging.getLogger("layerwatch.monitor")

#: a frame is one layer late when its anomalous area against the previous layer is at most this share of
#: its area against its own layer
LAG_EXPLAINED_SHARE = 0.25

#: how far from the previous layer's own area a change beside the print may lie and still be that layer, mm
BESIDE_MARGIN_MM = 2.0

def counts_toward_pause(res: LayerResult, policy: PolicySettings) -> bool:
    """Whether an analysed layer's result could count toward a pause (the lag check runs only then).

    True for an ``ok`` result past ``skip_first_layers`` with at least ``min_area_mm2`` (and
    one 1 mm^2) of anomalous area (the anomalous blocks' whole tiles, as the policy asks), with more anomalous area outside the footprint than
    ``strong_outside_area_mm2``, or with at least ``outside_pause_mm2`` of change beside the
    print (the scene channel), each when its rule is on.
    """
    if res.status != "ok" or res.layer < max(1, policy.skip_first_layers):
        return False
    strong, beside = policy.strong_outside_area_mm2, policy.outside_pause_mm2
    return (_tiles_mm2(res) >= _least_area(policy)
            or bool(strong) and res.outside_area_mm2 > strong
            or bool(beside) and res.outside_anomalous_mm2 >= beside)


def lag_checkable(pipeline: Any) -> bool:
    """Whether the pipeline gives what the late-camera check needs (references, top views, analysis settings)."""
    return all(hasattr(pipeline, n) for n in ("reference", "top_view", "topview", "config"))


def _tiles_mm2(res: LayerResult) -> float:
    """Image area of the anomalous blocks' whole tiles, mm^2: what the policy's minimum-area test asks.

    S_A (``anomalous_area_mm2``) plus the share of the tiles it leaves out (``uncounted_mm2``,
    0 with ``anomalous_area = "tiles"``), as :func:`~layerwatch.pipeline.policy.layer_alarm`
    is given it: a layer the policy can alarm on must reach the lag check.
    """
    return float(res.anomalous_area_mm2) + float(res.uncounted_mm2)


def _least_area(policy: PolicySettings) -> float:
    """Anomalous HOG area that counts, mm^2 (the policy's ``min_area_mm2``, at least 1)."""
    return max(policy.min_area_mm2, 1.0)


def _beside_explained(res: LayerResult, previous: np.ndarray, here: np.ndarray, topview: Any,
                      policy: PolicySettings) -> bool:
    """Whether the scene channel's change beside the print is what layer ``k - 1`` shows and layer ``k`` does not.

    ``previous``, ``here``: top-view footprints (bool, (H, W)) of layers ``k - 1`` and ``k``.
    Only there can a frame one layer late differ beside layer ``k``'s print (a first layer's
    skirt or brim, a ledge where the part narrows). A region counts as explained when that
    area, within :data:`BESIDE_MARGIN_MM`, covers at least half of its area inside its
    bounding box; the change not explained must stay below ``outside_pause_mm2``.
    """
    if not policy.outside_pause_mm2 or res.outside_anomalous_mm2 < policy.outside_pause_mm2:
        return True
    r = max(1, round(BESIDE_MARGIN_MM * topview.px_per_mm))
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    only_before = previous & ~cv2.dilate(here.astype(np.uint8), kernel).astype(bool)
    near = cv2.dilate(only_before.astype(np.uint8), kernel)
    px_mm2 = 1.0 / topview.px_per_mm**2
    left = 0.0
    for reg in res.outside_regions:
        corners = topview.to_px(np.array(reg.bbox_mm, np.float64).reshape(2, 2))
        (u0, v0), (u1, v1) = np.floor(corners.min(axis=0)) - r, np.ceil(corners.max(axis=0)) + r
        box = near[max(int(v0), 0):max(int(v1) + 1, 0), max(int(u0), 0):max(int(u1) + 1, 0)]
        if float(box.sum()) * px_mm2 < 0.5 * reg.area_mm2:
            left += reg.area_mm2
    return left < policy.outside_pause_mm2


@dataclass(frozen=True)
class LagVerdict:
    """What the previous layer's reference says about a frame.

    Attributes
    ----------
    lagged : bool
        The frame shows layer ``layer - 1``: a camera fault.
    area_mm2 : float
        Anomalous area against the frame's own layer, mm^2.
    previous_area_mm2 : float
        Anomalous area against the previous layer, mm^2.
    message : str
        One line for the record (empty when not ``lagged``).
    previous : LayerResult or None
        The analysis of the frame against the previous layer (its ``layer`` and ``z`` those
        of the previous layer).
    """

    lagged: bool
    area_mm2: float
    previous_area_mm2: float
    message: str = ""
    previous: LayerResult | None = None

    @property
    def figures(self) -> dict[str, float]:
        """The two areas, for ``LayerResult.frame_quality``."""
        return {"lag_area_mm2": round(self.area_mm2, 3), "lag_previous_area_mm2": round(self.previous_area_mm2, 3)}


def previous_layer_explains(pipeline: Any, photo: np.ndarray, res: LayerResult, policy: PolicySettings,
                            top: tuple[np.ndarray, np.ndarray] | None = None,
                            own: Any = None) -> LagVerdict | None:
    """Analyse ``photo`` (taken for ``res.layer``) against the previous layer's reference.

    Parameters
    ----------
    pipeline : LayerPipeline
        Anything with ``reference(i)``, ``top_view(photo, z, box=None)``, ``topview`` and
        ``config.analysis`` (:class:`~layerwatch.pipeline.step.LayerPipeline`, or a wrapper
        that forwards them); its state (scene channel, last top view) is not touched.
    photo : ndarray, uint8, shape (h, w, 3)
        The frame, as the pipeline was given it.
    res : LayerResult
        The pipeline's result for this frame against its own layer.
    policy : PolicySettings
        ``min_area_mm2``: below it on both layers, anomalous area is noise (see the module notes).
    top : (ndarray, ndarray), optional
        ``pipeline.top_view(photo, z)`` on the previous layer's plane when the caller has it.
    own : Reference, optional
        ``pipeline.reference(res.layer)`` when the caller holds it: a pipeline that memoises one
        reference drops it for the previous layer's, and would render it again.

    Returns
    -------
    LagVerdict or None
        With the analysis against the previous layer; None when there is no previous layer or
        the pipeline cannot be asked.
    """
    k = int(res.layer)
    if k < 1 or not lag_checkable(pipeline):
        return None
    ref = pipeline.reference(k - 1)
    top_prev, valid = top if top is not None else pipeline.top_view(photo, ref.z)
    before = analyze_layer(top_prev, ref.image, ref.footprint, pipeline.topview, pipeline.config.analysis,
                           valid=valid, layer=k - 1, z=ref.z)
    here, prev = _tiles_mm2(res), _tiles_mm2(before)
    least = _least_area(policy)
    hog_explained = prev <= LAG_EXPLAINED_SHARE * here or (prev < least and here < least)
    here_ref = own if own is not None else pipeline.reference(k)
    lagged = hog_explained and _beside_explained(res, ref.footprint, here_ref.footprint, pipeline.topview, policy)
    msg = (f"lagged frame: the photo of layer {k} shows layer {k - 1} ({prev:.0f} mm^2 anomalous against "
           f"layer {k - 1}, {here:.0f} mm^2 against layer {k}), judged against layer {k - 1}; the camera "
           "delivers frames one layer late: take the snapshot from the camera itself, not a cached stream, "
           "or add a delay before it" if lagged else "")
    return LagVerdict(lagged, here, prev, msg, before)


#: a block of the zone changed between two frames when the NCC of their band-passed top views is below this
CHANGED_NCC = 0.5
#: at most this share of the zone's blocks changed: nothing new was printed (simulated example part: 0-0.01
#: for a new exposure of the same layer or a stall)
STILL_SHARE = 0.05
#: at least this share changed: new material (0.21-0.34 where a thin wall grew by a layer, 0.56-0.92 on
#: infill and on the first layer); in between, no verdict
PRINTED_SHARE = 0.15
#: fewest textured blocks of the zone the progress between two frames is judged on
MIN_PROGRESS_BLOCKS = 4
#: side of the blocks the progress is judged on, top-view px
PROGRESS_BLOCK_PX = 8
#: Gaussian (top-view px) applied to the high-passed top views: sensor noise out, bead and edge texture kept
PROGRESS_BLUR_PX = 1.5
#: the zone where a layer's new material may change the picture: its footprint dilated by this, mm
PROGRESS_MARGIN_MM = 1.0
#: a first layer whose anomaly ratio against its reference is at least this is not in the picture yet (a
#: camera late from the job start shows the empty bed there; a first layer that failed is the first-layer
#: check's, and a frame a check failed on is never excused)
MISSING_FIRST_LAYER_RATIO = 0.25


@dataclass(frozen=True)
class Progress:
    """What changed between two frames where the G-code printed in between.

    Attributes
    ----------
    changed : float
        Share of the zone's textured blocks whose band-passed texture changed (zero-mean NCC
        below :data:`CHANGED_NCC`, :func:`~layerwatch.analysis.extrusion.block_ncc`): near 0
        when the surface is the same (new light and noise aside), high where new beads
        replaced it; ``nan`` when not judged.
    blocks : int
        Textured blocks compared.
    """

    changed: float
    blocks: int

    @property
    def judged(self) -> bool:
        """Enough texture in the zone to say anything."""
        return self.blocks >= MIN_PROGRESS_BLOCKS and bool(np.isfinite(self.changed))

    @property
    def printed(self) -> bool:
        """New material where the G-code printed: the print (or the late picture of it) advanced."""
        return self.judged and self.changed >= PRINTED_SHARE

    @property
    def still(self) -> bool:
        """Nothing new where the G-code printed: a stall, or the first frame of a stream that fell behind."""
        return self.judged and self.changed <= STILL_SHARE


def _disk(radius_px: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))


def progress_between(top: np.ndarray, before: np.ndarray, valid: np.ndarray, zone: np.ndarray) -> Progress:
    """How much two top views of the same plane differ on ``zone`` (:class:`Progress`).

    Parameters
    ----------
    top, before : ndarray, uint8, shape (h, w)
        Grey top views of this frame and of the frame before, warped to the same plane.
    valid : ndarray, bool, shape (h, w)
        Pixels this frame saw (the camera did not move, so the frame before saw them too).
    zone : ndarray, bool, shape (h, w)
        Where the layers printed between the two frames lie (footprints dilated by
        :data:`PROGRESS_MARGIN_MM`).
    """
    a, b = (cv2.GaussianBlur(highpass(t), (0, 0), PROGRESS_BLUR_PX) for t in (top, before))
    ncc, scored = block_ncc(a, b, zone & valid, PROGRESS_BLOCK_PX)
    n = int(scored.sum())
    return Progress(float(np.mean(ncc[scored] < CHANGED_NCC)) if n else float("nan"), n)


@dataclass(frozen=True)
class LateCheck:
    """What :meth:`LateStream.check` made of one analysed frame.

    Attributes
    ----------
    judged : LayerResult or None
        The frame's analysis against the layer it shows (layer ``k - 1``), carrying this
        trigger's layer and height, when the frame is excused as late; None: judge it as it is.
    why : str
        Why a frame the previous layer explains is judged as it is (empty otherwise).
    alert : bool
        The lag just became consistent (``after_n`` excused frames): alert once.
    progress : Progress or None
        Progress since the previous analysed frame (None: no earlier frame).
    verdict : LagVerdict or None
        The previous layer's verdict (None: the frame would not count toward a pause).
    """

    judged: LayerResult | None = None
    why: str = ""
    alert: bool = False
    progress: Progress | None = None
    verdict: LagVerdict | None = None


@dataclass
class _Seen:
    """The last analysed frame near the print: its top view on the plane of ``layer``, cropped to ``box``.

    Its valid mask is not kept: the camera did not move (or the gate refuses the frame), so the next
    frame's, on a plane a layer away, stands for it.
    """

    layer: int
    z: float
    box: tuple[slice, slice]
    top: np.ndarray
    zone: np.ndarray  # the layer's footprint dilated by PROGRESS_MARGIN_MM, cropped to ``box`` (bool)


class LateStream:
    """Is the stream one layer late? Told over the series, not from one photo.

    One photo cannot tell a camera that delivers the previous layer's picture from a
    layer that added nothing (a clog, a part torn off into spaghetti): both look like
    the previous layer's reference. Two consecutive frames can. A late camera still
    shows progress: frame ``k`` (the picture of layer ``k - 1``) differs from frame
    ``k - 1`` (layer ``k - 2``) by new material where layer ``k - 1`` printed; a stalled
    print shows none. And a camera falls behind at some frame: that frame repeats the
    previous picture (it shows no progress, or the gate refuses it as a repeat).

    A frame explained by the previous layer's reference (:func:`previous_layer_explains`)
    is *excused* (judged against the layer it shows) when the pipeline's own checks
    (nothing extruded, first layer) found nothing in it and the series says so:

    * **a late frame**: it shows progress since the previous analysed frame where the
      layers in between printed (:func:`progress_between` on the zone of their
      footprints), and the stream *slipped* before it: since the last frame that its own
      layer explained better than the previous one (:meth:`judged`), a frame showed no
      progress or was unusable (refused by the gate, no image), or the first layer was not in the
      picture (a camera late from the job start shows the empty bed there); or
    * **the first frame of a slip**: it shows no progress at all (the previous picture
      again, as a new exposure; the gate refuses the same picture with only new noise),
      and the frame before it did show progress. One such frame cannot be told from the
      first layer of a stall; it is taken as the slip, and the next frame tells: a stall
      shows no progress again and is judged as it is (and the nothing-extruded check,
      whose verdict is never excused, compares it with the photo two layers back).

    A camera on time never slips, so a failure that makes layer ``k`` look like layer
    ``k - 1`` while the part still grows is judged as it is; a print that stopped
    growing shows no progress twice in a row, so from its second layer it is judged as
    it is; spaghetti stays anomalous against the layer the frame shows, so an excused
    frame still pauses for it.

    Parameters
    ----------
    after_n : int
        Excused frames in a row before :meth:`excused` says to alert ("camera lagging").
    """

    def __init__(self, after_n: int) -> None:
        self.after_n = int(after_n)
        self.count = 0
        self.alerted = False
        #: the stream slipped and has not been judged as it was since: its frames may be one layer late
        self.slipped = False
        #: the last frame showed no progress or was unusable (a second such frame is a stall's)
        self.still = False
        self._seen: _Seen | None = None

    # ---------------------------------------------------------------- frames
    def remember(self, pipeline: Any, layer: int, top: np.ndarray | None, ref: Any = None) -> None:
        """Keep frame ``layer``'s grey top view (warped on that layer's plane) around the zone the next frame
        is compared on (a copy of that box only: a farm holds one per printer); ``ref``: the layer's
        reference when the caller holds it."""
        if top is None:
            return
        ref = ref if ref is not None else pipeline.reference(layer)
        zone = _zone(ref.footprint, pipeline.topview)
        box = _box(zone, pipeline.topview)
        if box is None:
            return
        self._seen = _Seen(layer, ref.z, box, np.ascontiguousarray(top[box]), np.ascontiguousarray(zone[box]))

    def progress(self, pipeline: Any, photo: np.ndarray, layer: int) -> Progress | None:
        """Progress of frame ``layer`` since the remembered frame (this frame warped on that frame's plane,
        only in the remembered box); None when no frame is remembered."""
        seen = self._seen
        if seen is None or layer <= seen.layer:
            return None
        top, valid = pipeline.top_view(photo, seen.z, seen.box)
        zone = seen.zone.copy()  # the layers printed between the two pictures (a dilation of a union is
        for i in range(seen.layer + 1, layer):  # the union of the dilations: no re-render of the remembered one)
            zone |= _zone(pipeline.reference(i).footprint, pipeline.topview)[seen.box]
        return progress_between(top, seen.top, valid, zone)

    def interrupted(self) -> None:
        """A frame was unusable (repeat, black, no image...): the stream may come back late."""
        self.slipped = self.still = True

    def judged(self, res: LayerResult, verdict: LagVerdict | None, progress: Progress | None) -> None:
        """After a frame judged as it was: its own layer explained it better than the previous one
        (``verdict``), the stream is taken to be on time again; ``progress`` showed nothing new, or the
        first layer is not in the picture (:data:`MISSING_FIRST_LAYER_RATIO`): it may have slipped here."""
        if verdict is not None and verdict.previous_area_mm2 > verdict.area_mm2:
            self.slipped = False
            self.count, self.alerted = 0, False
        self._saw(progress)
        if res.layer == 0 and res.anomaly_ratio >= MISSING_FIRST_LAYER_RATIO:
            self.slipped = True

    def _saw(self, progress: Progress | None) -> None:
        self.still = progress is not None and progress.still
        self.slipped = self.slipped or self.still

    # ---------------------------------------------------------------- verdict
    def check(self, pipeline: Any, photo: np.ndarray, res: LayerResult, policy: PolicySettings,
              excuse: bool = True) -> LateCheck:
        """One analysed frame (``res``: ``status`` ok, against its own layer): is it a late one to excuse?

        Measures the progress since the remembered frame, runs :func:`previous_layer_explains`
        when ``res`` would count toward a pause, decides (:meth:`excuse`; ``excuse=False``:
        never), updates the series and remembers this frame. Raises what the pipeline raises.
        """
        counts = counts_toward_pause(res, policy)
        progress = self.progress(pipeline, photo, res.layer)
        # this layer's reference, held across the previous layer's (a farm pipeline memoises one reference:
        # it would render this one again, ~25 ms, on every frame that counts toward a pause)
        own = pipeline.reference(res.layer) if counts else None
        verdict = previous_layer_explains(pipeline, photo, res, policy, own=own) if counts else None
        self.remember(pipeline, res.layer, _top_of(pipeline, photo, res), own)
        seen, keep = self._seen, getattr(pipeline, "keep_top_view", None)
        if keep is not None and seen is not None and seen.layer == res.layer:  # the next frame's progress box
            keep(photo, seen.z, seen.box)
        lagged = verdict is not None and verdict.lagged
        why = self.excuse(verdict, progress, res) if verdict is not None and lagged else None
        if lagged and why is None and not excuse:
            why = "[frame_quality] excuse_late_frames is off"
        if not lagged or why is not None:
            self.judged(res, verdict, progress)
            text = f"the photo looks like layer {res.layer - 1} (a late camera?) but is judged as it is: {why}"
            return LateCheck(None, text if why else "", False, progress, verdict)
        assert verdict is not None and verdict.previous is not None and progress is not None  # lagged, excused
        judged = verdict.previous
        judged.layer, judged.z, judged.photo_ms = res.layer, res.z, res.photo_ms
        judged.message = verdict.message + ("; no change since the previous frame: the first late frame, or nothing "
                                            "printed on this layer (the next frame tells)" if progress.still else "")
        judged.frame_quality = {**verdict.figures, **self.figures(progress)}
        return LateCheck(judged, "", self.excused(progress), progress, verdict)

    def excuse(self, verdict: LagVerdict, progress: Progress | None, res: LayerResult) -> str | None:
        """Why a frame the previous layer explains is *not* excused, or None when it is (module notes)."""
        if res.failed_check:
            return f"the {res.failed_check.replace('_', '-')} check failed on it"
        if progress is None or not progress.judged:
            return "no earlier frame to tell a late camera from a layer that printed nothing"
        if progress.still:  # the slip itself, unless the frame before showed nothing new either
            return None if not self.still else (
                f"nothing new since the previous frame, twice in a row ({progress.changed:.0%} of the surface "
                "changed): nothing extruded, or the print stopped growing")
        if not progress.printed:
            return (f"{progress.changed:.0%} of the surface changed since the previous frame: too little to tell "
                    "new material from new light")
        if not self.slipped:
            return "the camera was on time so far (no repeated or unusable frame before it)"
        return None

    @staticmethod
    def figures(progress: Progress | None) -> dict[str, float]:
        """The progress figures for ``LayerResult.frame_quality``."""
        if progress is None:
            return {}
        return {"lag_progress_changed": round(progress.changed, 3), "lag_progress_blocks": progress.blocks}

    def excused(self, progress: Progress) -> bool:
        """Count one excused frame; True exactly when the lag just became consistent (alert once)."""
        self._saw(progress)
        self.count += 1
        due = self.count >= self.after_n and not self.alerted
        self.alerted = self.alerted or due
        return due


def _top_of(pipeline: Any, photo: np.ndarray, res: LayerResult) -> np.ndarray:
    """The analysed photo's grey top view on its layer's plane (the pipeline's, or warped)."""
    top = getattr(pipeline, "last_top", None)
    return top if top is not None else pipeline.top_view(photo, pipeline.reference(res.layer).z)[0]


def _zone(footprint: np.ndarray, topview: Any) -> np.ndarray:
    """``footprint`` dilated by :data:`PROGRESS_MARGIN_MM` (bool, same shape)."""
    r = max(1, round(PROGRESS_MARGIN_MM * topview.px_per_mm))
    fp = np.asarray(footprint, bool)
    out = np.zeros(fp.shape, bool)
    rows, cols = np.flatnonzero(fp.any(axis=1)), np.flatnonzero(fp.any(axis=0))
    if rows.size == 0:
        return out
    # dilated on the footprint's box grown by r only: nothing farther from the footprint is reached, and the
    # dilation's border (below every value) adds nothing where the whole image has zeros: the same mask
    h, w = fp.shape
    box = (slice(max(int(rows[0]) - r, 0), min(int(rows[-1]) + r + 1, h)),
           slice(max(int(cols[0]) - r, 0), min(int(cols[-1]) + r + 1, w)))
    out[box] = cv2.dilate(fp[box].view(np.uint8), _disk(r)) > 0
    return out


def _box(mask: np.ndarray, topview: Any) -> tuple[slice, slice] | None:
    """Bounding box of ``mask`` grown by :data:`PROGRESS_MARGIN_MM` (rows, cols), None when empty."""
    rows, cols = np.any(mask, axis=1), np.any(mask, axis=0)
    if not rows.any():
        return None
    r = max(1, round(PROGRESS_MARGIN_MM * topview.px_per_mm))
    (v0, v1), (u0, u1) = np.flatnonzero(rows)[[0, -1]], np.flatnonzero(cols)[[0, -1]]
    h, w = mask.shape
    return slice(max(v0 - r, 0), min(v1 + r + 1, h)), slice(max(u0 - r, 0), min(u1 + r + 1, w))
