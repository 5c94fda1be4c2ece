"""First-layer inspection: is the first layer on the bed where the G-code put it?

The first layer decides the print: a missing line, a corner that did not
stick or a nozzle that extruded nothing is cheap to stop now and expensive
later. With the empty-bed photo, the photo of layer 1 (index 0) shows it
directly: on the layer's footprint (eroded by ``margin_mm``: the beads'
rounded edges), every block must differ from the empty bed, because it is
covered with plastic.

Both photos are warped to the top view of the first layer's plane, the light
is fitted on the bed beside the footprint (dilated by ``OUTSIDE_MM``) with the
scene channel's normalisation
(:func:`~layerwatch.analysis.scene_change.photometric_fit`), and the block
residuals (:func:`~layerwatch.analysis.scene_change.change_blocks`) on the
footprint are held against the noise threshold of the bed beside it. A
footprint block above it is **covered**.

* **coverage**: covered blocks over footprint blocks; below ``min_coverage``
  the layer failed; below :data:`NOTHING_COVERAGE` nothing was extruded
  (region kind ``nothing_extruded``);
* **missing areas**: connected footprint blocks that look like the empty
  bed, at least ``max_missing_mm2``: a missing line or patch inside the
  footprint (kind ``infill_defect``), or at its outline, where a lifted or
  unstuck corner leaves the bed bare (kind ``detachment``).

Dark filament on a dark bed hardly differs from it: when the footprint's
block residuals (90th percentile) stay below :data:`MIN_CONTRAST` times the bare bed's threshold,
only "nothing extruded" (coverage below :data:`NOTHING_COVERAGE`) is judged;
missing lines are not (the simulator's dark variants: ``evaluate/checks.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from layerwatch.analysis.block_masks import blocks_to_pixels, close_gaps
from layerwatch.analysis.check_settings import FirstLayerSettings
from layerwatch.analysis.result import Region
from layerwatch.analysis.scene_change import (
    SATURATED,
    change_blocks,
    change_regions,
    channel_max,
    photometric_fit,
    to_working,
)
from layerwatch.analysis.settings import SceneSettings
from layerwatch.geometry.topview import TopView

__all__ = ["FirstLayerCheck", "MIN_CONTRAST", "NOTHING_COVERAGE", "OUTSIDE_MM", "inspect_first_layer"]

#: coverage below which the first layer counts as not extruded at all (clean dark-on-dark layers: >= 0.17)
NOTHING_COVERAGE = 0.1
#: 90th percentile of the footprint's block residuals over the bare bed's threshold below which missing lines
#: are not judged (the percentile: half the footprint may be missing; on the simulator, seed 0: dark filament
#: 1.1-2.2, orange or white filament 12.8-17)
MIN_CONTRAST = 4.0
#: the light and the noise are measured on the bed this far beside the footprint, mm
OUTSIDE_MM = 3.0


@dataclass
class FirstLayerCheck:
    """The verdict of the first-layer inspection.

    Attributes
    ----------
    ok : bool or None
        ``None`` when the layer could not be judged (no footprint seen, no bed beside it).
    coverage : float
        Covered footprint blocks over footprint blocks, in [0, 1].
    contrast : float
        90th percentile of the footprint blocks' residuals over the bare bed's threshold.
    regions : list of Region
        Missing areas (bed mm, largest first) with their kind.
    message : str
    missing : ndarray, bool, shape (H, W) or None
        Top-view pixels of the footprint that look like the empty bed.
    """

    ok: bool | None
    coverage: float = 1.0
    contrast: float = 0.0
    regions: list[Region] = field(default_factory=list)
    message: str = ""
    missing: np.ndarray | None = None


def _disc(mm: float, px_per_mm: float) -> np.ndarray:
    k = int(round(2 * mm * px_per_mm)) | 1
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))


def _type_regions(regions: list[Region], footprint: np.ndarray, topview: TopView, coverage: float) -> None:
    """``nothing_extruded`` when nothing covers the footprint; else ``detachment`` at its outline, ``infill_defect`` inside."""
    if coverage < NOTHING_COVERAGE:
        for r in regions:
            r.kind, r.kind_confidence = "nothing_extruded", round(1.0 - coverage / NOTHING_COVERAGE, 3)
        return
    ring = footprint & ~cv2.erode(footprint.astype(np.uint8), _disc(1.5, topview.px_per_mm)).astype(bool)
    for r in regions:
        (u0, v0), (u1, v1) = np.round(topview.to_px(np.array([[r.bbox_mm[0], r.bbox_mm[3]],
                                                              [r.bbox_mm[2], r.bbox_mm[1]]]))).astype(int)
        touches = ring[max(v0, 0): v1 + 1, max(u0, 0): u1 + 1].any()
        r.kind, r.kind_confidence = ("detachment", 0.5) if touches else ("infill_defect", 0.6)


def inspect_first_layer(top: np.ndarray, bed_top: np.ndarray, footprint: np.ndarray, topview: TopView,
                        settings: FirstLayerSettings, block_px: int = 8,
                        valid: np.ndarray | None = None) -> FirstLayerCheck:
    """Judge the first layer's photo against its footprint and the empty bed (module notes).

    Parameters
    ----------
    top, bed_top : ndarray, uint8, shape (H, W, 3) or (H, W)
        Top views of the first layer's plane: the photo after layer 1 and the empty-bed photo.
    footprint : ndarray, bool, shape (H, W)
        The first layer's footprint from the G-code.
    topview : TopView
    settings : FirstLayerSettings
    block_px : int
        Block side, top-view px.
    valid : ndarray, bool, shape (H, W), optional
        Top-view pixels the camera sees.

    Returns
    -------
    FirstLayerCheck
    """
    size = (topview.shape[1], topview.shape[0])
    a, b = to_working(np.asarray(top), size), to_working(np.asarray(bed_top), size)
    seen = (channel_max(a) > 0) & (channel_max(b) > 0) & (channel_max(a) < SATURATED) & (channel_max(b) < SATURATED)
    if valid is not None:
        seen &= np.asarray(valid, bool)
    fp = np.asarray(footprint, np.uint8)
    inside = cv2.erode(fp, _disc(settings.margin_mm, topview.px_per_mm)).astype(bool) & seen
    outside = ~cv2.dilate(fp, _disc(OUTSIDE_MM, topview.px_per_mm)).astype(bool) & seen
    if inside.sum() < block_px * block_px or outside.sum() < 50 * block_px * block_px:
        return FirstLayerCheck(None, message="first layer not inspected: the camera does not see it or the bed beside it")
    st = SceneSettings(block_px=block_px, min_change=settings.min_change, min_region_mm2=0.0)
    ratio, _ = photometric_fit(a, b, outside)
    bed = change_blocks(a, b, outside, ratio, st)  # the noise of the bare bed beside the layer
    layer = change_blocks(a, b, inside, ratio, st)
    covered = layer.scored & (layer.score > bed.threshold)
    n = int(layer.scored.sum())
    if n == 0:
        return FirstLayerCheck(None, message="first layer not inspected: its footprint is too thin to judge")
    coverage = float(covered.sum()) / n
    contrast = float(np.percentile(layer.score[layer.scored], 90)) / max(bed.threshold, 1e-6)
    bare = layer.scored & ~covered
    missing = close_gaps(blocks_to_pixels(bare, block_px, topview.shape, fill=False), 2 * block_px + 1) & inside
    regions = [r for r in change_regions(missing, np.where(missing, 0.0, 1.0).astype(np.float32), topview, 0.0)
               if r.area_mm2 >= settings.max_missing_mm2]
    _type_regions(regions, fp.astype(bool), topview, coverage)
    faint = contrast < MIN_CONTRAST and coverage >= NOTHING_COVERAGE
    if faint:  # dark filament on a dark bed: thin coverage is the camera's, not the layer's
        return FirstLayerCheck(True, coverage, contrast, [], (
            f"first layer hardly differs from the bed (contrast {contrast:.1f} x the bed's noise): only "
            "'nothing extruded' is judged"), missing)
    if coverage >= settings.min_coverage and not regions:
        return FirstLayerCheck(True, coverage, contrast, [], f"first layer covers {coverage:.0%} of its footprint",
                               missing)
    if coverage < NOTHING_COVERAGE:
        what = "nothing was extruded (clog, no filament, nozzle too high?)"
    elif regions:
        big = regions[0]
        what = (f"{big.area_mm2:.0f} mm^2 of it look like the empty bed at ({big.centroid_mm[0]:.0f}, "
                f"{big.centroid_mm[1]:.0f}) mm ({'lifted or unstuck corner' if big.kind == 'detachment' else 'missing lines'}?)")
    else:
        what = "lines are missing or thin (under-extrusion, nozzle too high?)"
    return FirstLayerCheck(False, coverage, contrast, regions,
                           f"first layer failed: it covers {coverage:.0%} of its footprint; {what}", missing)
