"""The "changed as predicted" channel across a print: the previous photo's texture and the per-layer verdict.

:class:`LayerChange` keeps the high-passed texture of the last analysed photo
of the print and, for each new analysed photo, asks
:mod:`layerwatch.analysis.layer_change` which pixels of the new layer's
footprint look as they did then. It works on the nothing-extruded check's
working image and camera rays (:class:`~layerwatch.pipeline.checks.JobChecks`:
``size``, ``box``, ``maps``), so the projection is the same.

A photo the pipeline did not analyse (rejected frame, error) neither is judged
nor becomes the previous photo; a skipped layer is covered because the
previous photo is the last analysed one, whatever its layer (the parallax
is the height printed since). The first photo of a print, and a photo whose
previous photo shows no texture to calibrate on (black, blank), get no
verdict (``LayerResult.layer_change.judged`` is False with a note). A layer
that looks as before over most of its footprint (more than
:data:`MAX_UNCHANGED_SHARE` of the judged pixels) is not a local defect but
nothing extruded, the nothing-extruded check's failure: no region here. Nor
is a layer that the failure typer found moved (regions typed layer shift or
detachment, :data:`~layerwatch.analysis.failure_kinds.MOVED_KINDS`, of at least
``moved_min_mm2`` together): its planned place looks as before because the
layer lies elsewhere, and the moved outline already marks it. Smaller moved
regions (a registration that took part of the layer's pattern for a move, or a
move too small to pause on) leave the channel on: only the unchanged pixels
within :data:`MOVED_MARGIN_MM` of their outline are left out.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import cv2
import numpy as np

from layerwatch.analysis.extrusion import box_texture
from layerwatch.analysis.failure_kinds import MOVED_KINDS
from layerwatch.analysis.layer_change import (
    LayerChangeSettings,
    add_unchanged,
    apart_from,
    blocks_on_top,
    clipped_box,
    moved_pixels,
    parallax_px,
    unchanged_regions,
    window_change,
)
from layerwatch.analysis.result import LayerChangeStats, LayerResult
from layerwatch.analysis.scene_change import predicted_change
from layerwatch.analysis.seen_past import BLIND_SHARE, past_share
from layerwatch.analysis.wall_runs import WALL_BLIND_SHARE, wall_top, wall_verdict
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.topview import TopView
from layerwatch.geometry.warp import TopViewWarper
from layerwatch.pipeline.checks import JobChecks

__all__ = ["MAX_UNCHANGED_SHARE", "MOVED_MARGIN_MM", "NEAR_MARGIN_MM", "LayerChange"]

#: the new layer's projection grown by this (mm) is never a quiet block (the noise is calibrated off it)
NEAR_MARGIN_MM = 1.5
#: more than this share of the judged pixels unchanged: the whole layer looks as before, which is the
#: nothing-extruded check's failure (clog, run-out; ``[extrusion]``), not a local defect: no region here
MAX_UNCHANGED_SHARE = 0.5
#: unchanged pixels within this of a small moved region's outline are the motion's, not a defect, mm
MOVED_MARGIN_MM = 1.0
#: ``footprint(j) -> (top-view bool mask of layer j, z bottom, z top)`` (the pipeline's references)
FootprintFn = Callable[[int], "tuple[np.ndarray, float, float]"]


class LayerChange:
    """The channel's state for one print (module notes).

    Parameters
    ----------
    checks : JobChecks
        The pipeline's checks: their working image size, crop box and camera rays.
    topview : TopView
    warper : TopViewWarper
        The pipeline's warper (its maps carry unchanged pixels to the top view).
    toolpath : Toolpath
        The job's G-code (what each layer prints: walls or infill).
    settings : LayerChangeSettings
    moved_min_mm2 : float or callable
        Moved regions (layer shift, detachment) of at least this area together switch the
        channel off for the layer (module notes), mm^2; or a function that gives it, read at
        every layer. The pipeline passes one that reads its policy's ``min_area_mm2`` (the
        smallest area that pauses), so a settings edit applies from the next layer on.
    """

    def __init__(self, checks: JobChecks, topview: TopView, warper: TopViewWarper, toolpath: Toolpath,
                 settings: LayerChangeSettings, moved_min_mm2: float | Callable[[], float] = 5.0) -> None:
        self.checks, self.topview, self.warper = checks, topview, warper
        self.toolpath, self.settings = toolpath, settings
        if callable(moved_min_mm2):
            self._moved_min = moved_min_mm2
        else:
            area = float(moved_min_mm2)
            self._moved_min = lambda: area
        self.new_print()

    @property
    def moved_min_mm2(self) -> float:
        """The moved area that switches the channel off for a layer, mm^2 (its current value)."""
        return float(self._moved_min())

    def new_print(self) -> None:
        """Forget the previous photo (a new print, or the single-photo mode's reset)."""
        #: ``(layer, z top mm, texture, clipped pixels)`` of the last analysed photo (working box)
        self._previous: tuple[int, float, np.ndarray, np.ndarray] | None = None
        #: image shift per mm of height printed, working px (:func:`parallax_px`; the camera's, computed once)
        self._shift_per_mm: tuple[float, float] | None = None

    def judge(self, res: LayerResult, photo: np.ndarray, index: int, footprint: FootprintFn) -> None:
        """Judge an analysed photo against the previous one; write regions, a% and ``res.layer_change``."""
        if res.status != "ok":
            return
        t0 = time.perf_counter()
        maps = self.checks.maps  # sets checks.box
        texture = self.checks.texture_of(index)  # the nothing-extruded check's, when it ran on this photo
        if texture is None:
            texture = np.ascontiguousarray(box_texture(photo, self.checks.size, self.checks.box))
        fp, _, z = footprint(index)
        clipped = clipped_box(photo, self.checks.size, self.checks.box)
        previous, self._previous = self._previous, (index, z, texture, clipped)
        stats = LayerChangeStats(previous_layer=-1 if previous is None else previous[0])
        res.layer_change = stats
        try:
            if previous is None or previous[0] >= index:
                stats.note = "no earlier photo of this print to compare with"
                return
            self._compare(res, stats, texture, clipped, previous, fp, z, index, maps, photo)
        finally:
            # the time goes with the step's other timings, not into the record (records compare equal across runs)
            res.timings_ms["layer_change"] = round((time.perf_counter() - t0) * 1e3, 3)

    def _compare(self, res: LayerResult, stats: LayerChangeStats, texture: np.ndarray, clipped: np.ndarray,
                 previous: tuple[int, float, np.ndarray, np.ndarray], fp: np.ndarray, z: float, index: int,
                 maps: tuple[np.ndarray, np.ndarray], photo: np.ndarray) -> None:
        st = self.settings
        z_before = previous[1]
        planes = self.checks.planes()  # each plane's top-view coordinates, computed once (with the checks' in a frame)
        surface = predicted_change(fp, np.array([z]), maps, self.topview, 0.0, planes)
        near = predicted_change(fp, np.array([z_before, z]), maps, self.topview, NEAR_MARGIN_MM, planes)
        if self._shift_per_mm is None:
            self._shift_per_mm = parallax_px(maps, z, 1.0)
        shift = (self._shift_per_mm[0] * (z - z_before), self._shift_per_mm[1] * (z - z_before))
        stats.parallax_px = round(float(np.hypot(*shift)), 3)
        glare = previous[3] | clipped if previous[3].shape == clipped.shape else clipped
        change = window_change(texture, previous[2], surface, near, shift, st, glare)
        if change is None:
            stats.note = "too little texture beside the print to calibrate the noise (dark or blank photo?)"
            return
        past = past_share(surface, fp, z, z_before, maps, self.topview, previous[2], change.noise,
                          st.min_snr, st.window_px)
        blind = past >= BLIND_SHARE
        if blind.any():  # the previous photo saw past the part there (a skirt behind the far wall): no verdict
            change.judged &= ~blind
            change.unchanged &= ~blind
        if st.wall_run_mm > 0:  # a perimeter pixel counts only in a run along the wall
            walls = predicted_change(wall_top(self.toolpath, index, self.topview), np.array([z]), maps, self.topview, 0.0,
                                     planes)
            tx, ty = planes[float(z)]
            ppm = self.topview.px_per_mm
            change.unchanged = wall_verdict(change, surface, walls, shift, (tx / ppm, ty / ppm), st, maps[1],
                                            past >= WALL_BLIND_SHARE)
        stats.judged, stats.noise = True, round(change.noise, 4)
        stats.px_judged, stats.px_unchanged = int(change.judged.sum()), int(change.unchanged.sum())
        if stats.px_unchanged > MAX_UNCHANGED_SHARE * stats.px_judged:
            stats.note = "most of the layer looks as in the previous photo: left to the nothing-extruded check"
            return
        if not change.unchanged.any():
            return
        moved = [r for r in res.regions if r.kind in MOVED_KINDS]
        if moved and sum(r.area_mm2 for r in moved) >= self.moved_min_mm2:
            # a shifted or detached layer leaves its planned place as it was: the typer's moved
            # outline already marks that area, a thin-wall or infill region there would be wrong
            stats.note = "the part moved (a region is typed layer shift or detachment): its unchanged area is the motion's"
            return
        h, w = np.asarray(photo).shape[:2]
        map1, map2, valid = self.warper.maps(z, (w, h))
        source = cv2.convertMaps(map1, map2, cv2.CV_32FC1)
        size = self.checks.size
        rows, cols = self.checks.box
        top = blocks_on_top(change.unchanged, 1, (rows.start or 0, cols.start or 0),
                            (size[0] / w, size[1] / h), source, fp & valid)
        if moved:  # small moved regions: only the unchanged pixels at their outline are theirs
            top = apart_from(top, moved_pixels(moved, self.topview), MOVED_MARGIN_MM, self.topview)
        mask, regions = unchanged_regions(top, fp, self.toolpath, index, self.topview, st.min_area_mm2)
        stats.added_mm2 = round(add_unchanged(res, mask, regions, self.topview), 3)
        stats.unchanged_mm2 = round(float(sum(r.area_mm2 for r in regions)), 3)
