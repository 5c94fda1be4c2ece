"""Say what failed: type every failing region of a layer and measure how far the part moved.

:class:`FailureTyper` gives each region of a :class:`~layerwatch.analysis.result.LayerResult`
(the HOG channel's ``regions`` on the printed layer and the scene channel's
``outside_regions`` beside it) a kind of
:data:`~layerwatch.analysis.failure_kinds.FAILURE_KINDS` with a confidence,
and a layer shift or a moved/detached part its displacement in bed mm. It
uses only what the per-layer step already has: the photo's colour top view,
the rendered reference and footprint of the layer, the layer's plan (which
toolpath features lie under a region) and the regions of the previous
analysed photo of the same print.

Evidence (per region, all scale-free or in mm)
----------------------------------------------
* **Whole-part motion** (:func:`part_motion`): the top layer's edges in the
  reference registered against the photo's edges in the top view by phase
  correlation (translation, sub-pixel) inside the footprint's
  neighbourhood, then a rotation search, then ECC (rotation and
  translation together). A part whose top layer sits at
  least :data:`MOVE_MIN_MM` away from where the plan puts it has moved: a
  *layer shift* (the gantry skipped steps: a pure translation) or, when it
  also turned by :data:`ROTATION_MIN_DEG` or more, a *detachment* (a part
  knocked loose turns as it slides). Regions within the moved part's reach
  (:meth:`_Scene.near_moved`; for a shift also the reach of the print's
  lower layers: a shift moves every object printed after it) take that kind, the displacement and the moved part's area
  (:attr:`~layerwatch.analysis.result.Region.outline_mm`): for a layer
  shift where the layer is and should not be, and where it should be and is
  not (the layers below stay put and the shifted top looks like the planned
  one where the two overlap); for a detachment the whole part, every
  visible top of it (the layer and the lower layers beyond it), where the
  photo shows it and where the plan has it (:meth:`_Scene.detached_area`):
  all of a part that came off is out of place.
* **The new material and the shift that stays** (series mode,
  :meth:`FailureTyper._other_moves`): where the whole registration sees no
  move, the run's layer shift (a shift stays: every layer printed after it
  is off by the same vector, so the plate's other objects too) and then the
  place of the edges that are new since the print's previous photo
  (:class:`~layerwatch.analysis.part_registration.NewMaterial`: the unmoved
  layers below, whose zero-shift peak hides a shift's first layers on
  plates of small objects, are no new material) are tried. A shift is kept
  for the next photos only when the new material puts the layer there.
* **What the moved layer uncovered** (:meth:`_Scene.ledge`): the layers
  below where they were (the part's colour: a layer shift) or the bare bed
  (a detached part took its first layers with it). Only where the part's
  own lower layers (:func:`part_below`), carried by the same motion, do not
  reach: there a detached part on a wider base shows its moved base, the
  part's colour too, and only the turn tells the two apart.
* **Where the moved layer arrived** (:meth:`_Scene.arrived`): a registered
  move whose new place (beyond the planned outline and the part's lower
  layers) shows the bare bed is no move: the registration locked on
  something else, e.g. an object lying on the part. Both motion tests read
  the part's filament colour where nothing failed (:attr:`_Scene.filament_colour`):
  an object that covers a small part's whole layer (a lump on one cube of a
  plate) is not the part's colour, and the plate's other objects show it.
* **Where**: the share of the region outside the part's closed outline
  (the footprint with the gaps of sparse infill closed; material where the
  plan has none: strands, objects, a moved part) against inside (material
  missing or disturbed where the plan prints). The scene channel's regions
  beside the printed layer count as outside.
* **Colour**: how far the region's material (its pixels unlike the bare
  bed) lies from the printed part's colour (median CIELAB distance,
  lightness half weighted against shading), or, where at least 5 % of the
  region is unlike both the bed and the part, how far those pixels lie
  (an object on the part's own wider base, whose material unlike the bed
  is mostly that base). A foreign body is another material; strands and a
  pit in the infill are the part's own filament.
* **Texture**: mean edge strength of the photo against the reference in the
  region; beside the part (where the reference is bare bed) many thin
  edges are strands. Inside the part it is no evidence: a pit shows the
  layers below, as many edges as strands on the part.
* **Plan under it**: the share of wall segments (perimeters) against infill
  segments of the layer's G-code inside the region: a gap in a wall is a
  *thin-wall* defect, one in the infill an *infill defect*.
* **The object itself** (:meth:`_Scene.object_outline`, for a region typed
  foreign body, after typing): its pixels unlike both the bed and the part
  above the noise around its box, as the region's outline; its blocks'
  tiles and box padding otherwise mark several times the object.
* **History** (series mode): a region at the same place in the previous
  photo that grew by more than half is spaghetti (the clump grows with every
  layer), one that kept its area is a resting object.

Rules
-----
Each kind gets a score, a sum of the evidence terms above with unit weights
(:func:`kind_scores`); the region's kind is the highest, its confidence the
softmax share of that score (temperature 0.5). The weights are unit
weights and the colour and move thresholds physical choices (a shift below
0.75 mm is within the registration noise of a 6.67 px/mm top view); the
registration's peak and rotation constants were set by hand on
development photos of the simulator, none fitted to the evaluation's
prints. The evaluation reports the resulting confusion matrix on held-out
simulated prints (``docs/evaluation/report.md``); on real photos the
colour and texture evidence is what carries over, the simulator's own
shading is not used.

Cost
----
Nothing is measured on a layer without regions. Otherwise each quantity is
computed when a region first needs it and on the smallest crop that gives
the whole view's value (``_Scene``): the part's colour on the footprint's
box, the bed's colour as the exact median from 8-bit CIELAB histograms
(whole view minus the footprint's neighbourhood), the closed outline on the
footprint's box (and only for regions on the printed layer), edge strengths
on each region's box; the registration as described in
:mod:`~layerwatch.analysis.part_registration`. The evidence is the same as
computed over the whole top view (``benchmarks/typing_equivalence.py``:
every region of the evaluation typed alike, same confidence and
displacement), about a quarter of the time.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from layerwatch.analysis.block_masks import close_gaps, fill_holes, touching
from layerwatch.analysis.failure_kinds import MOVED_KINDS, UNKNOWN
from layerwatch.analysis.histogram import middle_values
from layerwatch.analysis.part_registration import (
    EDGE_PAD_PX,
    MOVE_MAX_MM,
    MOVE_MIN_MM,
    ROTATION_GAIN,
    ROTATION_MIN_DEG,
    ROTATIONS_DEG,
    SECOND_PEAK,
    NewMaterial,
    PartMotion,
    crop_box,
    edges,
    evidence_motion,
    mask_box,
    moved_area,
    pad_box,
    part_motion,
    top_from_plan,
)
from layerwatch.analysis.region_outline import Outline, outline_mm, region_box
from layerwatch.analysis.result import LayerResult, Region
from layerwatch.gcode.toolpath import FEATURES, Toolpath, part_mask
from layerwatch.geometry.topview import TopView

__all__ = ["MOVE_MAX_MM", "MOVE_MIN_MM", "ROTATIONS_DEG", "ROTATION_GAIN", "ROTATION_MIN_DEG", "SECOND_PEAK",
           "FailureTyper", "PartMotion", "RegionEvidence", "kind_scores", "part_below", "part_motion", "part_seen", "seen_heights", "region_evidence"]

#: CIELAB distance (lightness half weighted) above which a pixel is unlike a reference colour
COLOUR_DELTA = 22.0
#: median CIELAB distance of a region's material from the part: 0 (the part's filament) to 1 (another material)
PART_DELTA = (20.0, 40.0)
#: median CIELAB distance from the part of the pixels unlike both bed and part: 0 (the part's shading) to 1 (another
#: material), mm-free; twice and three times :data:`COLOUR_DELTA`
OTHER_DELTA = (44.0, 66.0)
#: smallest share of a region's pixels unlike both the bed and the part that is read as another material
OTHER_MIN_SHARE = 0.05
#: robust standard deviations of the ring around a foreign body's box above which a pixel is the object's
NOISE_SIGMAS = 2.5
#: side of the square closing a foreign body's pixels, mm; and the ring around its box that gives the noise, mm
OBJECT_CLOSE_MM, NOISE_RING_MM = 1.0, 2.0
#: smallest area of a foreign body's pixels that replaces its blocks, mm^2
OBJECT_MIN_MM2 = 2.0
#: a connected part of the footprint this large (mm^2) is an object of its own when a move's arrival is judged
PLATE_OBJECT_MM2 = 4.0
#: the area a moved layer uncovered is trimmed by this much on each side before its colour counts, mm
#: (slivers along its edges are the registration's error and the moved walls' parallax, not a ledge or the bed)
LEDGE_TRIM_MM = 0.75
#: a registered move stands only when at least this share of the area the layer newly covers looks like the part
#: (a real move: about half to all of it; a registration locked on an object: bare bed nearly everywhere)
ARRIVED_MIN = 0.25
#: smallest share of the region's own area (its failing blocks or changed pixels) the object's pixels, grown to the
#: blocks that measured them (:data:`OBJECT_BLOCK_MM`), must cover
OBJECT_MIN_SHARE = 0.5
#: side of the blocks the channels measure a region in, mm: the scene channel's change blocks (8 working px, about
#: 2 mm on the bed) and the HOG blocks (2 x 2 cells of 1.2 mm); a region's area is its blocks' (or their tiles'),
#: which a thin object only partly fills
OBJECT_BLOCK_MM = 2.0
#: how far beyond a moved part (on top of its displacement) a region is still taken for the moved part, mm
MOVED_REACH_MM = 3.0

_WALL = tuple(FEATURES.index(n) for n in ("perimeter", "external_perimeter"))
_INFILL = tuple(FEATURES.index(n) for n in ("infill", "solid_infill", "top_solid_infill", "bridge"))


@dataclass(frozen=True)
class RegionEvidence:
    """The measured evidence of one region (see the module notes).

    Attributes
    ----------
    outside : float
        Share of the region outside the layer's footprint, 0-1.
    foreign : float
        How unlike the printed part its material is (colour), 0 (the part's filament) to 1.
    texture : float
        log2 of the photo's mean edge strength over the reference's in the region.
    wall : float
        Share of wall segments among the plan's segments in the region, 0-1 (0.5 when none).
    growth : float
        log2 of the area over that of the same region in the previous photo; NaN without one.
    near_moved_part : bool
        Within the reach of a part that moved (:attr:`PartMotion.moved`).
    ledge : float
        Share of the area the moved layer uncovered that shows the part's
        material, not the bed (:meth:`_Scene.ledge`), 0-1; 0.5 = no evidence.
    """

    outside: float
    foreign: float
    texture: float
    wall: float
    growth: float = float("nan")
    near_moved_part: bool = False
    ledge: float = 0.5


def _lab_u8(top_bgr: np.ndarray) -> np.ndarray:
    """OpenCV's 8-bit CIELAB of a BGR (or grey) image, uint8 (H, W, 3): L scaled to 0-255, a/b offset by 128."""
    img = np.asarray(top_bgr, np.uint8)
    bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2LAB)


def _lab(lab_u8: np.ndarray) -> np.ndarray:
    """:func:`_lab_u8` as float32 with L in 0-100 (a/b offset by 128: differences only)."""
    lab = lab_u8.astype(np.float32)
    lab[..., 0] *= 100.0 / 255.0
    return lab


def _lab_hist(lab_u8: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """Histograms of the three 8-bit CIELAB channels over ``mask`` (all pixels when None), float64 (3, 256)."""
    m = None if mask is None else np.ascontiguousarray(mask).view(np.uint8)
    return np.stack([cv2.calcHist([lab_u8], [c], m, [256], [0, 256]).reshape(-1) for c in range(3)]).astype(np.float64)


def _hist_median(hist: np.ndarray) -> np.ndarray:
    """Per-channel median of the 8-bit CIELAB values counted in ``hist`` (3, 256), as :func:`_lab` scales them.

    The same as ``np.median(_lab(values), axis=0)`` of the values (the mean
    of the two middle values for an even count), from the counts alone.
    """
    lo, hi = (np.array(v, np.float32) for v in zip(*(middle_values(h) for h in hist), strict=True))
    scale = np.array([100.0 / 255.0, 1.0, 1.0], np.float32)
    return (lo * scale + hi * scale) / np.float32(2.0)


def _lab_distance(lab: np.ndarray, colour: np.ndarray, lightness_weight: float = 0.5) -> np.ndarray:
    """CIELAB distance of colours ``lab`` (..., 3) from ``colour`` (3,), lightness weighted (half: shading)."""
    d = lab - colour
    return np.sqrt((lightness_weight * d[..., 0]) ** 2 + d[..., 1] ** 2 + d[..., 2] ** 2)


def _unlike(lab: np.ndarray, colour: np.ndarray) -> np.ndarray:
    return _lab_distance(lab, colour) > COLOUR_DELTA


class _Scene:
    """Per-photo quantities the regions' evidence reads, each computed when first needed and on crops only.

    The part's colour reads the footprint's box, the bed's colour the whole
    view (as 8-bit CIELAB histograms: its exact median without sorting),
    the closed outline the footprint's box, the edge strengths each
    region's box (padded by :data:`~layerwatch.analysis.part_registration.EDGE_PAD_PX`).
    Every crop is padded so that its values are those of the whole top view.
    """

    def __init__(self, top_bgr: np.ndarray, top: np.ndarray, reference: np.ndarray, footprint: np.ndarray,
                 topview: TopView, valid: np.ndarray | None,
                 footprint_box: tuple[int, int, int, int] | None = None,
                 below: Callable[[], np.ndarray | None] | None = None,
                 seen: Callable[[], np.ndarray | None] | None = None,
                 failing: list[tuple[slice, slice]] | None = None) -> None:
        self.topview = topview
        self._below = below
        self._part_seen = seen
        self._failing = failing or []
        self.top_bgr, self.top, self.reference = top_bgr, top, reference
        self.fp = np.asarray(footprint, bool)
        self.shape = self.fp.shape
        self.valid = None if valid is None else np.asarray(valid, bool)
        self.fp_box = mask_box(self.fp) if footprint_box is None else footprint_box
        self.k = max(3, int(round(2.0 * topview.px_per_mm)) | 1)
        self._moved: tuple[PartMotion, np.ndarray] | None = None
        self._ledge: tuple[PartMotion, float] | None = None

    def near_moved(self, box: tuple[slice, slice], motion: PartMotion) -> bool:
        """Whether ``box`` lies within the reach of the part that moved (``motion``'s magnitude + :data:`MOVED_REACH_MM`).

        The reach is measured from the layer's footprint box; for a move that
        did not turn (a layer shift) also from the print's lower layers
        (:func:`part_below`, every object of the plate): a shift displaces
        the gantry, so everything printed after it is off by the same amount,
        the plate's other objects too (KISSlicer prints two objects in turns:
        the layer registered is often the other object's), and the change
        beside those objects is the shifted print, not strands. A part that
        turned came off alone: only its own footprint counts.
        """
        if not motion.moved or self.fp_box is None:
            return False
        reach = int(round((motion.magnitude_mm + MOVED_REACH_MM) * self.topview.px_per_mm))
        fp_box = pad_box(self.fp_box, reach, self.shape)
        if (box[0].start < fp_box[0].stop and fp_box[0].start < box[0].stop
                and box[1].start < fp_box[1].stop and fp_box[1].start < box[1].stop):
            return True
        if motion.turned or self._below is None:
            return False
        below = self._below()
        if below is None:
            return False
        crop = pad_box((box[0].start, box[0].stop, box[1].start, box[1].stop), reach, self.shape)
        return bool(below[crop].any())

    def seen(self, box: tuple[slice, slice]) -> np.ndarray:
        """Pixels of ``box`` the camera saw, bool."""
        if self.valid is None:
            return np.ones((box[0].stop - box[0].start, box[1].stop - box[1].start), bool)
        return self.valid[box]

    @cached_property
    def lab_u8(self) -> np.ndarray:
        """8-bit CIELAB of the colour top view (H, W, 3)."""
        return _lab_u8(self.top_bgr)

    @cached_property
    def part_colour(self) -> np.ndarray | None:
        """Median CIELAB of the part: its footprint eroded by 2 mm (all of it when that leaves <= 50 px); None: no part seen."""
        if self.fp_box is None:
            return None
        crop = pad_box(self.fp_box, self.k, self.shape)
        fp, seen = self.fp[crop], self.seen(crop)
        if not (fp & seen).any():
            return None
        inner = cv2.erode(fp.astype(np.uint8), np.ones((self.k, self.k), np.uint8)).astype(bool) & seen
        return _hist_median(_lab_hist(self.lab_u8[crop], inner if inner.sum() > 50 else fp & seen))

    @cached_property
    def filament_colour(self) -> np.ndarray | None:
        """Median CIELAB of the part's filament where nothing failed; the motion tests' part colour.

        The footprint eroded by 2 mm outside the failing regions' boxes; when that leaves
        <= 50 px (a region covers the layer: an object lying on a small part of a plate),
        the plate's other objects (the part's lower layers, :func:`part_below`, not
        connected to the layer's footprint, eroded by 2 mm) outside the boxes: one
        filament prints the whole plate. :attr:`part_colour` when neither leaves more.
        :attr:`part_colour` is the colour of the footprint as the photo shows it; when an
        object covers the footprint that is the object's, and a registration locked on the
        object's edges would find its own new place "part-coloured".
        """
        if self.fp_box is None:
            return None
        crop = pad_box(self.fp_box, self.k, self.shape)
        failing = np.zeros(self.shape, bool)
        for box in self._failing:
            failing[box] = True
        inner = cv2.erode(self.fp[crop].view(np.uint8), np.ones((self.k, self.k), np.uint8)).astype(bool)
        inner &= self.seen(crop) & ~failing[crop]
        if np.count_nonzero(inner) > 50:
            return _hist_median(_lab_hist(self.lab_u8[crop], inner))
        below = self._below() if self._failing and self._below is not None else None
        if below is not None and below.any():
            others = below & ~touching(below, self.fp)
            found = mask_box(others)
            if found is not None:  # eroded on its box (padded: the erosion's border is the box's, not the view's)
                rows, cols = pad_box(found, self.k, self.shape)
                kept = cv2.erode(others[rows, cols].view(np.uint8), np.ones((self.k, self.k), np.uint8)) > 0
                kept &= ~failing[rows, cols] & self.seen((rows, cols))
                if np.count_nonzero(kept) > 50:
                    return _hist_median(_lab_hist(self.lab_u8[rows, cols], kept))
        return self.part_colour

    @cached_property
    def bed_colour(self) -> np.ndarray | None:
        """Median CIELAB of the seen pixels beyond the footprint widened by 4 x 2 mm; None when <= 50 px."""
        hist = _lab_hist(self.lab_u8, None if self.valid is None else self.valid)
        if self.fp_box is not None:  # take out the footprint's neighbourhood, counted on its box
            kk = 4 * self.k
            crop = pad_box(self.fp_box, kk, self.shape)
            near = cv2.dilate(self.fp[crop].astype(np.uint8), np.ones((kk, kk), np.uint8)).astype(bool)
            hist -= _lab_hist(self.lab_u8[crop], near & self.seen(crop))
        return _hist_median(hist) if hist[0].sum() > 50 else None

    @cached_property
    def _closed(self) -> tuple[tuple[slice, slice], np.ndarray] | None:
        """The part's outline with the gaps of sparse infill (up to 3 mm) closed, on its box (padded), bool."""
        if self.fp_box is None:
            return None
        k2 = max(3, int(round(3.0 * self.topview.px_per_mm)) | 1)
        crop = pad_box(self.fp_box, k2 + 1, self.shape)
        return crop, close_gaps(self.fp[crop], k2)

    @cached_property
    def _solid(self) -> tuple[tuple[slice, slice], np.ndarray] | None:
        """The closed outline (:attr:`_closed`) with its holes filled ("inside the part"), on its box."""
        if self._closed is None:
            return None
        crop, closed = self._closed
        return crop, fill_holes(closed)

    @cached_property
    def outline(self) -> np.ndarray:
        """The closed outline (:attr:`_closed`) in the whole view, bool (H, W)."""
        out = np.zeros(self.shape, bool)
        if self._closed is not None:
            crop, closed = self._closed
            out[crop] = closed
        return out

    @cached_property
    def objects(self) -> list[np.ndarray]:
        """The layer's objects: the footprint's connected parts of at least :data:`PLATE_OBJECT_MM2`, each with
        its own gaps closed as :attr:`outline` closes them, bool (H, W) each (objects of a plate standing
        closer than the closing's 3 mm are one in :attr:`outline`)."""
        n, labels, stats, _ = cv2.connectedComponentsWithStats(self.fp.view(np.uint8), connectivity=8)
        k2 = max(3, int(round(3.0 * self.topview.px_per_mm)) | 1)
        out = []
        for i in range(1, n):
            x, y, w, h, area = (int(v) for v in stats[i])
            if area < PLATE_OBJECT_MM2 * self.topview.px_per_mm ** 2:
                continue
            crop = pad_box((y, y + h, x, x + w), k2 + 1, self.shape)
            obj = np.zeros(self.shape, bool)
            obj[crop] = close_gaps(labels[crop] == i, k2)
            out.append(obj)
        return out

    def moved_area(self, motion: PartMotion) -> np.ndarray:
        """:func:`moved_area` of the closed outline, bool (H, W) (kept for the last ``motion`` asked)."""
        if self._moved is None or self._moved[0] != motion:
            self._moved = (motion, moved_area(self.outline, motion, self.topview))
        return self._moved[1]

    def moved_outline(self, motion: PartMotion) -> Outline:
        """Where the moved layer is and should not be, and where it should be and is not, bed mm (:meth:`moved_area`)."""
        if self._closed is None or not motion.moved:
            return ()
        return outline_mm(self.moved_area(motion), self.topview)

    def shifted_outline(self, motion: PartMotion, block: np.ndarray | None, tol_mm: float) -> Outline:
        """A layer shift's area in bed mm: where the shifted layers make the view other than planned.

        ``block``: the heights of the shifted layers as the camera sees them
        where the plan puts them (:func:`seen_heights` from the first layer the
        shift was seen on), float32 (H, W) mm; None: the layer's closed
        outline alone (:meth:`moved_outline`). The area is where ``block`` and
        ``block`` carried by :func:`top_from_plan` differ by more than
        ``tol_mm``: the overhang, the place left, and the walls facing the
        camera here and there; where the shifted top covers the planned one
        the camera sees the same surface at the same height.
        """
        if block is None or not motion.moved:
            return self.moved_outline(motion)
        carried = cv2.warpAffine(np.ascontiguousarray(block, np.float32), top_from_plan(motion, self.topview),
                                 self.shape[::-1], flags=cv2.INTER_NEAREST)
        return outline_mm(np.abs(block - carried) > tol_mm, self.topview)

    def detached_area(self, motion: PartMotion) -> np.ndarray:
        """A detached part's area: all of the part as seen, where the plan has it and where the photo shows it, bool (H, W).

        The part is :func:`part_seen` (every layer projected through the camera
        centre: its tops and the walls facing the camera) where the typer knows
        the camera, else the part's lower layers (:func:`part_below`) where the
        plan puts them; in both cases only what touches the layer's closed
        outline (a plate's other objects stay on the bed), with the layer's
        outline (holes filled) added. It is carried to where the photo shows
        it by :func:`top_from_plan` (the tilt of a part that came off is not
        modelled). Empty when the part did not move.
        """
        if self._solid is None or not motion.moved:
            return np.zeros(self.shape, bool)
        crop, solid = self._solid
        part = np.zeros(self.shape, bool)
        part[crop] = solid
        rest = self._part_seen() if self._part_seen is not None else None
        if rest is None and self._below is not None:
            rest = self._below()
        if rest is not None and rest.any():
            part |= rest & touching(rest | part, part)
        carried = cv2.warpAffine(part.view(np.uint8), top_from_plan(motion, self.topview), self.shape[::-1],
                                 flags=cv2.INTER_NEAREST).astype(bool)
        return part | carried

    def detached_outline(self, motion: PartMotion) -> Outline:
        """:meth:`detached_area` in bed mm."""
        if not motion.moved:
            return ()
        return outline_mm(self.detached_area(motion), self.topview)

    def object_outline(self, r: Region) -> Outline:
        """A foreign body's own pixels in the region's box, as bed-mm polygons; ``()`` where none stand out.

        A pixel is the object's when its colour is unlike both the bare bed's
        and the part's median colour (the nearer CIELAB distance, lightness
        fully weighted: an object often differs in lightness only) by more
        than the noise of that distance: the larger
        of :data:`COLOUR_DELTA` and the median plus :data:`NOISE_SIGMAS`
        robust standard deviations (1.4826 MAD) of the seen pixels in a
        :data:`NOISE_RING_MM` ring one ring width off the box (both colours
        are this photo's, so exposure and white balance cancel). The pixels
        are looked for up to two ring widths beyond the box (an object reaches
        beyond the blocks that fired on it), closed by a
        :data:`OBJECT_CLOSE_MM` square, their holes filled (a glint on the
        object), and the parts that reach into the box are kept. ``()`` (the region keeps its blocks) when neither colour
        is known, the pixels cover less than :data:`OBJECT_MIN_MM2`, or, grown
        to the blocks that measured the region (a square of :data:`OBJECT_BLOCK_MM`:
        a 1 mm hex key fills about a third of each 2 mm block it crosses), less
        than :data:`OBJECT_MIN_SHARE` of the region's own area: then the colour
        test missed most of what the region measured (a dark object on a dark
        bed differs from it in lightness by less than the noise) and the
        region's blocks or box say more.
        """
        box = self.box(r)
        colours = [c for c in (self.bed_colour, self.part_colour) if c is not None]
        if box is None or not colours:
            return ()
        ring = int(round(NOISE_RING_MM * self.topview.px_per_mm))
        bounds = (box[0].start, box[0].stop, box[1].start, box[1].stop)
        pad = pad_box(bounds, 2 * ring, self.shape)
        dist = np.min([_lab_distance(_lab(self.lab_u8[pad]), c, 1.0) for c in colours], axis=0)
        inner, near = (np.zeros(dist.shape, bool) for _ in range(2))
        for m, b in ((inner, box), (near, pad_box(bounds, ring, self.shape))):
            m[b[0].start - pad[0].start: b[0].stop - pad[0].start, b[1].start - pad[1].start: b[1].stop - pad[1].start] = True
        seen = self.seen(pad)
        around = dist[~near & seen]
        thr = COLOUR_DELTA
        if around.size >= 20:
            med = float(np.median(around))
            thr = max(thr, med + NOISE_SIGMAS * 1.4826 * float(np.median(np.abs(around - med))))
        k = max(3, int(round(OBJECT_CLOSE_MM * self.topview.px_per_mm)) | 1)
        obj = ((dist > thr) & seen).view(np.uint8)  # up to 2 ring widths out: an object reaches beyond its blocks
        obj = fill_holes(close_gaps(obj, k))
        obj = touching(obj, inner)  # the parts that reach into the region's box
        px_mm2 = self.topview.px_per_mm ** 2
        n_obj = int(np.count_nonzero(obj))
        if n_obj < OBJECT_MIN_MM2 * px_mm2 or 2 * np.count_nonzero(dist[obj] > thr) <= n_obj:
            return ()  # too small, or mostly the closing's fill: a fringe of a low-contrast object
        kb = max(3, int(round(OBJECT_BLOCK_MM * self.topview.px_per_mm)) | 1)  # the blocks it fills, on average
        blocks = cv2.dilate(obj.view(np.uint8), np.ones((kb, kb), np.uint8))
        if np.count_nonzero(blocks) < OBJECT_MIN_SHARE * r.area_mm2 * px_mm2:
            return ()
        mask = np.zeros(self.shape, bool)
        mask[pad] = obj
        return outline_mm(mask, self.topview, min_area_mm2=OBJECT_MIN_MM2)

    def ledge(self, motion: PartMotion) -> float:
        """Share of the area a moved layer uncovered that shows the part's material rather than the bare bed, 0-1.

        Where the layer should be and is not (the closed outline minus the
        registered one, trimmed by :data:`LEDGE_TRIM_MM`), a layer shift leaves the
        layers below it (the part's material); a detached part, which moved
        with its first layers, leaves the bed, except where its own lower
        layers, moved with it, reach under that area (a part that narrows
        upward: a block on a wider base shows the moved base there, as a
        shift shows the layers below). Those pixels (the part below the
        layer, ``below``, carried by the same motion) are left out: only
        where the two explanations differ is the colour evidence. Each seen
        pixel counts for the nearer of the part's filament colour
        (:attr:`filament_colour`) and the bed's median colour. 0.5 (no
        evidence) when the part did not move, either colour is unknown, they
        are alike (within :data:`COLOUR_DELTA`) or fewer than 20 pixels are
        left.
        """
        if self._ledge is None or self._ledge[0] != motion:
            self._ledge = (motion, self._ledge_share(motion))
        return self._ledge[1]

    def arrived(self, motion: PartMotion) -> float:
        """Share of the area a moved layer newly covers that shows the part's material rather than the bare bed, 0-1.

        Where the registration puts the layer and the plan does not (the
        registered closed outline minus the planned one, trimmed by
        :data:`LEDGE_TRIM_MM`): a layer that really moved is there, whether
        it shifted or the part came off. Bare bed there means the
        registration locked on something else (an object on the part, the
        edges of another feature). Each seen pixel counts for the nearer of
        the part's filament colour (:attr:`filament_colour`: not the colour of
        an object covering the layer) and the bed's median colour. On a plate each object's new
        place counts for itself and the least share is returned: the move
        carried every object printed since (a clump of strands beside one
        object of a plate locked the registration on a move that leaves the
        others' new places on bare bed). 0.5 (no evidence) as in
        :meth:`ledge` (also where that area lies on the part's lower layers,
        which are the part's colour either way).
        """
        share = self._colour_share(motion, arrived=True)
        return 0.5 if share is None else share

    def arrival_seen(self, motion: PartMotion) -> float | None:
        """:meth:`arrived`, None where it has no evidence (instead of 0.5)."""
        return self._colour_share(motion, arrived=True)

    def _ledge_share(self, motion: PartMotion) -> float:
        share = self._colour_share(motion, arrived=False)
        return 0.5 if share is None else share

    def _colour_share(self, motion: PartMotion, arrived: bool) -> float | None:
        """:meth:`arrived` (``arrived``) or :meth:`ledge`; None where they say 0.5 (no evidence)."""
        if not motion.moved or self.filament_colour is None or self.bed_colour is None:
            return None
        part, bed = self.filament_colour, self.bed_colour
        if float(_lab_distance(part, bed)) <= COLOUR_DELTA:
            return None
        below = None if self._below is None else self._below()
        if arrived:
            # each object of a plate for itself (:attr:`objects`): the move carried all of them, so one that arrived
            # on bare bed says the registration locked on something else (a clump of strands beside another object)
            h, w = self.shape
            to_moved = top_from_plan(motion, self.topview)
            shares = []
            for obj in self.objects:
                carried = cv2.warpAffine(obj.view(np.uint8), to_moved, (w, h), flags=cv2.INTER_NEAREST)
                uncovered = (carried > 0) & ~self.outline
                if below is not None:  # on the part's lower layers (planned place): the part's colour either way
                    uncovered &= ~below
                shares.append(self._part_coloured_share(uncovered, part, bed))
            known = [v for v in shares if v is not None]
            return min(known) if known else None
        uncovered = self.outline & self.moved_area(motion)
        if below is not None:  # where the moved part's own lower layers would show: no evidence either way
            h, w = self.shape
            carried = cv2.warpAffine(below.view(np.uint8), top_from_plan(motion, self.topview), (w, h),
                                     flags=cv2.INTER_NEAREST)
            uncovered &= carried == 0
        return self._part_coloured_share(uncovered, part, bed)

    def _part_coloured_share(self, area: np.ndarray, part: np.ndarray, bed: np.ndarray) -> float | None:
        """Share of ``area``'s photo pixels (bool, top view) nearer the part's colour than the bed's, None (no
        evidence) when fewer than 20 are left after trimming ``LEDGE_TRIM_MM`` off its edges (slivers: registration error,
        walls' parallax) and keeping the valid pixels."""
        k = 2 * int(round(LEDGE_TRIM_MM * self.topview.px_per_mm)) + 1
        area = cv2.erode(area.view(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        if self.valid is not None:
            area &= self.valid
        if area.sum() < 20:
            return None
        lab = _lab(self.lab_u8[area])
        return float(np.mean(_lab_distance(lab, part) < _lab_distance(lab, bed)))

    def solid(self, box: tuple[slice, slice]) -> np.ndarray:
        """The closed outline (:attr:`_solid`) on ``box``, bool."""
        out = np.zeros((box[0].stop - box[0].start, box[1].stop - box[1].start), bool)
        if self._solid is not None:
            (cv, cu), solid = self._solid
            v0, v1 = max(box[0].start, cv.start), min(box[0].stop, cv.stop)
            u0, u1 = max(box[1].start, cu.start), min(box[1].stop, cu.stop)
            if v1 > v0 and u1 > u0:
                out[v0 - box[0].start: v1 - box[0].start, u0 - box[1].start: u1 - box[1].start] = \
                    solid[v0 - cv.start: v1 - cv.start, u0 - cu.start: u1 - cu.start]
        return out

    def texture(self, box: tuple[slice, slice], seen: np.ndarray) -> float:
        """log2 of the photo's mean edge strength over the reference's on the seen pixels of ``box``."""
        pad = pad_box((box[0].start, box[0].stop, box[1].start, box[1].stop), EDGE_PAD_PX, self.shape)
        inner = (slice(box[0].start - pad[0].start, box[0].stop - pad[0].start),
                 slice(box[1].start - pad[1].start, box[1].stop - pad[1].start))
        top_e, ref_e = edges(self.top[pad])[inner][seen], edges(self.reference[pad])[inner][seen]
        return float(np.log2((top_e.mean() + 1.0) / (ref_e.mean() + 1.0)))

    def outside(self, r: Region) -> float:
        """Share of the region's box (seen pixels) outside the part's closed outline."""
        box = self.box(r)
        if box is None:
            return float(r.outside_fraction)
        seen = self.seen(box)
        return float((~self.solid(box) & seen).sum() / max(int(seen.sum()), 1))

    def box(self, r: Region) -> tuple[slice, slice] | None:
        return region_box(r.bbox_mm, self.topview, self.shape)


def part_below(toolpath: Toolpath, index: int, topview: TopView) -> np.ndarray | None:
    """Top-view area of the part's layers below layer ``index`` as seen from above, bool (H, W); None when none.

    The union of the beads of layers ``0 .. index - 1`` (the part's own
    features: no skirt, brim or purge line), with the gaps of sparse infill
    (up to 3 mm) closed as in the layer's closed outline. Pixels are where
    the plan puts those layers; a detached part carries them with it.
    """
    if toolpath is None or not 0 < index < toolpath.n_layers:
        return None
    sl = slice(0, toolpath.layers[index - 1].seg_stop)
    keep = part_mask(toolpath.feature[sl])
    if not keep.any():
        return None
    return _closed_beads(toolpath.start[sl][keep], toolpath.end[sl][keep], toolpath.width[sl][keep], topview)


def part_seen(toolpath: Toolpath, index: int, topview: TopView, camera_mm: np.ndarray) -> np.ndarray | None:
    """The part up to layer ``index`` as the camera sees it in the top view of that layer's plane, bool (H, W).

    Where :func:`seen_heights` of layers ``0 .. index`` shows the part: its
    silhouette, the tops and the walls that face the camera. None when the
    layers print nothing of the part.
    """
    z = seen_heights(toolpath, index, topview, camera_mm)
    return None if z is None else z > 0


def seen_heights(toolpath: Toolpath, index: int, topview: TopView, camera_mm: np.ndarray,
                 first: int = 0) -> np.ndarray | None:
    """Height of the part's layer the camera sees at each pixel of the top view of layer ``index``'s plane, float32 (H, W).

    Every layer ``first .. index`` (the part's own features) projected through
    the camera centre ``camera_mm`` (bed mm, (3,)) onto the plane of layer
    ``index`` and drawn at its height ``z`` (mm), lower layers first: a lower
    layer lands nearer the camera's foot (parallax) and a higher one hides
    it, so the map holds the tops and the walls that face the camera. The
    gaps of sparse infill (up to 3 mm) are closed (grey closing). 0 where no
    layer of the range is seen; None when the range prints nothing of the part.
    """
    if toolpath is None or not 0 <= index < toolpath.n_layers:
        return None
    C = np.asarray(camera_mm, np.float64)
    z_top = toolpath.layers[index].z
    s = topview.px_per_mm
    out = np.zeros(topview.shape, np.float32)
    drawn = False
    for lay in toolpath.layers[min(max(int(first), 0), index): index + 1]:
        sl = slice(lay.seg_start, lay.seg_stop)
        keep = part_mask(toolpath.feature[sl])
        if not keep.any():
            continue
        k = (C[2] - z_top) / max(C[2] - lay.z, 1e-3)
        p0 = np.round(topview.to_px(C[:2] + (toolpath.start[sl][keep] - C[:2]) * k) * 4).astype(np.int32)
        p1 = np.round(topview.to_px(C[:2] + (toolpath.end[sl][keep] - C[:2]) * k) * 4).astype(np.int32)
        w = max(1, int(round(float(np.median(toolpath.width[sl][keep])) * s)))
        cv2.polylines(out, list(np.stack([p0, p1], axis=1)), False, float(lay.z), thickness=w, lineType=cv2.LINE_8,
                      shift=2)
        drawn = True
    if not drawn:
        return None
    k2 = max(3, int(round(3.0 * s)) | 1)
    return cv2.morphologyEx(out, cv2.MORPH_CLOSE, np.ones((k2, k2), np.uint8))


def _closed_beads(start: np.ndarray, end: np.ndarray, width: np.ndarray, topview: TopView) -> np.ndarray:
    """Beads ``start -> end`` (N, 2) bed mm drawn at their median width, the gaps up to 3 mm closed, bool (H, W)."""
    s = topview.px_per_mm
    p0 = np.round(topview.to_px(start) * 4).astype(np.int32)  # 2 fractional bits
    p1 = np.round(topview.to_px(end) * 4).astype(np.int32)
    w = max(1, int(round(float(np.median(width)) * s)))
    out = np.zeros(topview.shape, np.uint8)
    cv2.polylines(out, list(np.stack([p0, p1], axis=1)), False, 1, thickness=w, lineType=cv2.LINE_8, shift=2)
    k2 = max(3, int(round(3.0 * s)) | 1)
    return close_gaps(out, k2)


def _plan_wall_share(toolpath: Toolpath | None, index: int, bbox_mm: tuple[float, float, float, float]) -> float:
    """Share of wall segments among the wall and infill segments of layer ``index`` inside ``bbox_mm`` (0.5: none)."""
    if toolpath is None or not 0 <= index < toolpath.n_layers:
        return 0.5
    sl = toolpath.layer_slice(index)
    mid = 0.5 * (toolpath.start[sl] + toolpath.end[sl])
    x0, y0, x1, y1 = bbox_mm
    inside = (mid[:, 0] >= x0 - 1) & (mid[:, 0] <= x1 + 1) & (mid[:, 1] >= y0 - 1) & (mid[:, 1] <= y1 + 1)
    feats = toolpath.feature[sl][inside]
    walls, infill = int(np.isin(feats, _WALL).sum()), int(np.isin(feats, _INFILL).sum())
    return 0.5 if walls + infill == 0 else walls / (walls + infill)


def _unlike_part(lab: np.ndarray, scene: _Scene) -> float:
    """How unlike the printed part the region's material is, 0-1.

    The larger of two readings:

    * the :data:`PART_DELTA` ramp of the median CIELAB distance from the
      part's colour of the region's material: the pixels unlike the bare
      bed when they are at least 5 % of the region (a few strands over the
      bed), else all its pixels (an object the colour of the bed);
    * the :data:`OTHER_DELTA` ramp of the median distance from the part of
      the pixels unlike both the bed and the part, when they are at least
      :data:`OTHER_MIN_SHARE` of the region: an object lying on a lower
      surface of the part (a base wider than the layer), where the
      material unlike the bed is mostly the part's own surface around it.
      The part's own strands and shadows differ from its median colour by
      little more than :data:`COLOUR_DELTA` (shading); another material by
      far more.
    """
    if scene.part_colour is None or len(lab) == 0:
        return 0.0
    lo, hi = PART_DELTA
    other = 0.0
    if scene.bed_colour is not None:
        to_part = _lab_distance(lab, scene.part_colour)
        material = _unlike(lab, scene.bed_colour)
        unlike_both = material & (to_part > COLOUR_DELTA)
        if unlike_both.mean() >= OTHER_MIN_SHARE:
            o_lo, o_hi = OTHER_DELTA
            other = float(np.clip((float(np.median(to_part[unlike_both])) - o_lo) / (o_hi - o_lo), 0.0, 1.0))
        if material.mean() >= 0.05:
            lab = lab[material]
    dist = float(np.median(_lab_distance(lab, scene.part_colour)))
    return max(float(np.clip((dist - lo) / (hi - lo), 0.0, 1.0)), other)


def region_evidence(r: Region, scene: _Scene, wall: float, motion: PartMotion, outside: float) -> RegionEvidence:
    """Measure a region's evidence (module notes) in the photo of ``scene``."""
    box = scene.box(r)
    foreign, texture = 0.0, 0.0
    if box is not None:
        seen = scene.seen(box)
        if seen.any():
            foreign = _unlike_part(_lab(scene.lab_u8[box][seen]), scene) if scene.part_colour is not None else 0.0
            texture = scene.texture(box, seen)
    near = box is not None and scene.near_moved(box, motion)
    return RegionEvidence(outside=outside, foreign=foreign, texture=texture, wall=wall, near_moved_part=near)


def kind_scores(e: RegionEvidence, motion: PartMotion) -> dict[str, float]:
    """Score of each kind for a region with evidence ``e`` (module notes, unit weights).

    Returns
    -------
    dict of str to float
        ``spaghetti``, ``foreign_body``, ``detachment``, ``layer_shift``,
        ``infill_defect``, ``thin_wall``; higher = more likely.
    """
    grew = 0.0 if not np.isfinite(e.growth) else float(np.clip(e.growth / 0.6, -1.0, 1.0))
    edges = float(np.clip(e.texture, 0.0, 1.0))
    moved = 0.0
    if e.near_moved_part:
        moved = 2.5 + min(motion.magnitude_mm / MOVE_MIN_MM, 3.0) / 3.0
    # a clear turn is a detachment (a gantry cannot turn the part); a layer shift leaves the layers below
    # where they were (a ledge of the part's material), a detached part leaves the bed
    whole = (0.75 if motion.turned else -0.75) + (1.0 - 2.0 * e.ledge)
    inside = 1.0 - e.outside
    # edges count for strands beside the part only: a pit in the part also shows more edges (the layers below)
    return {
        "spaghetti": e.outside * (1.0 + edges) + 0.5 * edges + grew - 2.0 * e.foreign,
        "foreign_body": e.outside + 3.0 * e.foreign - max(grew, 0.0),
        "detachment": moved + (whole if moved else 0.0),
        "layer_shift": moved - (whole if moved else 0.0),
        "infill_defect": 2.0 * inside * (1.0 - e.wall) - e.foreign,
        "thin_wall": 2.0 * inside * e.wall - e.foreign,
    }


def _decide(scores: dict[str, float]) -> tuple[str, float]:
    names = list(scores)
    s = np.array([scores[k] for k in names], float)
    p = np.exp(2.0 * (s - s.max()))
    p /= p.sum()
    k = int(np.argmax(p))
    return names[k], float(round(p[k], 3))


def _match(r: Region, previous: list[Region]) -> Region | None:
    """The previous photo's region at the same place (centroid within the larger one's half diagonal, >= 5 mm)."""
    best, best_d = None, np.inf
    for q in previous:
        diag = max(math.hypot(r.bbox_mm[2] - r.bbox_mm[0], r.bbox_mm[3] - r.bbox_mm[1]),
                   math.hypot(q.bbox_mm[2] - q.bbox_mm[0], q.bbox_mm[3] - q.bbox_mm[1]))
        d = math.hypot(r.centroid_mm[0] - q.centroid_mm[0], r.centroid_mm[1] - q.centroid_mm[1])
        if d <= max(5.0, diag / 2) and d < best_d:
            best, best_d = q, d
    return best


class FailureTyper:
    """Type the failing regions of each analysed photo of a print (see the module notes).

    Parameters
    ----------
    toolpath : Toolpath, optional
        The job's plan (which segments lie under a region); without it walls
        and infill are not told apart (both scored equally).
    topview : TopView
        Geometry of the top views.
    """

    def __init__(self, toolpath: Toolpath | None, topview: TopView, camera_mm: np.ndarray | None = None) -> None:
        self.toolpath = toolpath
        self.topview = topview
        self.camera_mm = None if camera_mm is None else np.asarray(camera_mm, np.float64)
        self._seen: tuple[int, np.ndarray | None] | None = None
        #: first layer of the run of photos with a region typed as a moved part (series mode; a photo read as a
        #: detachment in a shifted print's run does not restart it), None: no moved part now
        self.shift_since: int | None = None
        #: the displacement of the run's last photo typed as a layer shift (a shift stays: every layer printed
        #: after it is off by the same vector), None: none in this run
        self.shift_motion: PartMotion | None = None
        #: the new material's correlation surfaces (:meth:`NewMaterial.evidence`) summed over the run's photos
        #: since its shift was placed: the vector carried is their peak (:meth:`_carried`)
        self.shift_evidence: np.ndarray | None = None
        self.previous: list[Region] = []
        self._below: tuple[int, np.ndarray | None] | None = None

    def _part_below(self, index: int) -> np.ndarray | None:
        """:func:`part_below` of layer ``index``, kept for the last layer asked (a moved part's photos come in a row)."""
        if self.toolpath is None:
            return None
        if self._below is None or self._below[0] != index:
            self._below = (index, part_below(self.toolpath, index, self.topview))
        return self._below[1]

    def _part_seen(self, index: int) -> np.ndarray | None:
        """:func:`part_seen` of layer ``index`` (None without a camera centre), kept for the last layer asked."""
        if self.toolpath is None or self.camera_mm is None:
            return None
        if self._seen is None or self._seen[0] != index:
            self._seen = (index, part_seen(self.toolpath, index, self.topview, self.camera_mm))
        return self._seen[1]

    def _shifted_block(self, index: int) -> np.ndarray | None:
        """:func:`seen_heights` of the layers since :attr:`shift_since` (None without a camera centre)."""
        if self.toolpath is None or self.camera_mm is None or self.shift_since is None:
            return None
        return seen_heights(self.toolpath, index, self.topview, self.camera_mm, first=self.shift_since)

    def _half_layer(self, index: int) -> float:
        """Half the height of layer ``index``, mm (0.1 when unknown): a seen height this much off is another layer."""
        if self.toolpath is None or not 0 <= index < self.toolpath.n_layers or self.toolpath.layers[index].height <= 0:
            return 0.1
        return 0.5 * float(self.toolpath.layers[index].height)

    def reset(self) -> None:
        """A new print: forget the previous photo's regions."""
        self.previous = []
        self.shift_since = None
        self.shift_motion = None
        self.shift_evidence = None

    def type_result(self, res: LayerResult, top_bgr: np.ndarray, top: np.ndarray, reference: np.ndarray,
                    footprint: np.ndarray, valid: np.ndarray | None = None,
                    previous: Callable[[tuple[slice, slice]], tuple[np.ndarray, np.ndarray] | None] | None = None,
                    ) -> PartMotion | None:
        """Fill ``kind``, ``kind_confidence`` and ``displacement_mm`` of every region of ``res``.

        Parameters
        ----------
        res : LayerResult
            An analysed layer (``regions`` and ``outside_regions``).
        top_bgr : ndarray, uint8, shape (H, W, 3) or (H, W)
            The photo's top view in colour (grey works, without colour evidence).
        top, reference : ndarray, uint8, shape (H, W)
            Grey top view and the layer's reference.
        footprint : ndarray, bool, shape (H, W)
        valid : ndarray, bool, shape (H, W), optional
        previous : callable, optional
            ``previous(box)``: the print's previous photo as a grey top view of this layer's plane
            on ``box`` (rows, columns of the top view) and its valid pixels, or None (series mode:
            the new material's place, :meth:`_other_moves`).

        Returns
        -------
        PartMotion or None
            The registration; None when there was no region to type (nothing
            is measured then) or the images could not be read (every region
            ``"unknown"``, confidence 0, said in ``res.message``).
        """
        regions = [*res.regions, *res.outside_regions]
        if not regions:
            self.previous = []
            return None
        try:
            fp_box = mask_box(footprint)
            crop_edges: dict = {}  # the registration's edge images, for the new material's
            motion = part_motion(top, reference, footprint, self.topview, valid, footprint_box=fp_box,
                                 hints=() if self.shift_motion is None else (self.shift_motion,), crop_edges=crop_edges)
            failing = [b for b in (region_box(r.bbox_mm, self.topview, footprint.shape) for r in regions) if b is not None]
            scene = _Scene(top_bgr, top, reference, footprint, self.topview, valid, fp_box,
                           below=lambda: self._part_below(res.layer), seen=lambda: self._part_seen(res.layer),
                           failing=failing)
            if motion.moved and scene.arrived(motion) < ARRIVED_MIN:  # bare bed where the layer would now be
                motion = PartMotion(peak=motion.peak)
            made: list[NewMaterial | None] = []

            def new_material() -> NewMaterial | None:  # made once, when first needed
                if not made:
                    made.append(self._new_material(previous, top, reference, footprint, valid, fp_box, crop_edges))
                return made[0]

            if not motion.moved:
                motion, placed = self._other_moves(motion, scene, new_material)
            else:  # a shift seen by the whole registration is kept for the next photos only when placed so
                placed = not motion.turned and (nm := new_material()) is not None and nm.placed(motion)
            for r in regions:
                self._type_region(r, any(r is q for q in res.outside_regions), res.layer, scene, motion)
            moved = [r for r in regions if r.kind in MOVED_KINDS]
            if not moved:
                self.shift_since = self.shift_motion = self.shift_evidence = None
            elif self.shift_since is None or self.shift_since > res.layer:
                self.shift_since = res.layer
            if placed and any(r.kind == "layer_shift" for r in moved):
                if self.shift_motion is None:  # placed on this photo: the run's evidence starts with it
                    self.shift_evidence = made[0].evidence() if made and made[0] is not None else None
                self.shift_motion = motion
            outlines: dict[str, Outline] = {}  # the moved part's area per kind, the same for each of its regions
            for r in moved:
                if r.kind not in outlines:
                    outlines[r.kind] = (scene.detached_outline(motion) if r.kind == "detachment"
                                        else scene.shifted_outline(motion, self._shifted_block(res.layer),
                                                                   self._half_layer(res.layer)))
                r.outline_mm = outlines[r.kind]
            for r in regions:  # a foreign body as its own pixels, not the blocks' tiles around it
                if r.kind == "foreign_body":
                    r.outline_mm = scene.object_outline(r)
        except (cv2.error, ValueError, IndexError) as exc:  # odd images: the regions stay reported, untyped
            for r in regions:
                r.kind, r.kind_confidence, r.displacement_mm, r.outline_mm = UNKNOWN, 0.0, None, ()
            note = f"failure typing skipped ({type(exc).__name__})"
            res.message = f"{res.message}; {note}" if res.message else note
            self.previous = regions
            return None
        self.previous = regions
        return motion

    def _new_material(self, previous: Callable[[tuple[slice, slice]], tuple[np.ndarray, np.ndarray] | None] | None,
                      top: np.ndarray, reference: np.ndarray, footprint: np.ndarray, valid: np.ndarray | None,
                      fp_box: tuple[int, int, int, int] | None, crop_edges: dict | None = None) -> NewMaterial | None:
        """:class:`NewMaterial` against the print's previous photo (``previous``), None without one
        (``crop_edges``: :func:`part_motion`'s edge images of the crop, reused)."""
        if previous is None or fp_box is None:
            return None
        before = previous(crop_box(footprint, self.topview, fp_box))
        if before is None:
            return None
        return NewMaterial(top, before[0], reference, footprint, self.topview, valid, before[1], fp_box, crop_edges)

    def _other_moves(self, motion: PartMotion, scene: _Scene,
                     new_material: Callable[[], NewMaterial | None]) -> tuple[PartMotion, bool]:
        """A layer shift that the whole registration (``motion``: no move) did not see, or ``motion``.

        Series mode only (``new_material``: the new edges since the print's previous photo).
        First the run's layer shift (:attr:`shift_motion`: a shift stays, every layer
        printed after it is off by the same vector) where its new place still shows the
        part (:meth:`_Scene.arrived` at least :data:`ARRIVED_MIN`, as for a registered
        move); then the place of the material printed since the previous photo
        (:meth:`NewMaterial.motion`: the unmoved layers below, whose zero-shift peak hides a
        shift's first layers, are no new material), taken when the new material puts the
        layer there rather than where planned (:meth:`NewMaterial.placed`) and its new place
        is seen to show the part (:meth:`_Scene.arrival_seen`: a move of under about twice
        :data:`LEDGE_TRIM_MM` leaves nothing to see and is not taken). Returns the motion and
        whether the new material placed it.
        """
        if self.shift_motion is not None and scene.arrived(self.shift_motion) >= ARRIVED_MIN:
            return self._carried(scene, new_material), True
        new = new_material()
        if new is None:
            return motion, False
        m = new.motion()
        seen = scene.arrival_seen(m) if m.moved else None
        if seen is not None and seen >= ARRIVED_MIN and new.placed(m):
            return m, True
        return motion, False

    def _carried(self, scene: _Scene, new_material: Callable[[], NewMaterial | None]) -> PartMotion:
        """The run's layer shift on a later photo of it: the peak of the new material's surfaces summed over the
        run (:meth:`NewMaterial.evidence`, :attr:`shift_evidence`) where its new place shows the part, else
        the vector carried.

        A shift stays: each photo after the onset measures the same vector again on the layer printed
        since, so their surfaces add up. The onset's layer alone can leave two peaks of the same height
        (Simplify3D's 2 mm shift ``s013``: 0.0056 and 0.0055, 1.9 mm apart); the next photos decide between
        them rather than carry the first one read. The vector carried changes only for another peak (at
        least :data:`MOVE_MIN_MM` away, the registration's noise being ~0.2 mm), not for its own peak's
        wander within that noise.
        """
        carried = self.shift_motion
        assert carried is not None
        if self.shift_evidence is None:
            return carried
        new = new_material()
        seen = None if new is None else new.evidence()
        if seen is None or seen.shape != self.shift_evidence.shape:
            return carried
        total = self.shift_evidence + seen
        m = evidence_motion(total, self.topview)
        if not m.moved or scene.arrived(m) < ARRIVED_MIN:
            return carried
        self.shift_evidence = total
        return m if math.hypot(m.dx_mm - carried.dx_mm, m.dy_mm - carried.dy_mm) >= MOVE_MIN_MM else carried

    def _type_region(self, r: Region, beside: bool, layer: int, scene: _Scene, motion: PartMotion) -> None:
        """Fill ``r.kind``, ``r.kind_confidence`` and ``r.displacement_mm`` (``beside``: a scene-channel region)."""
        outside = 1.0 if beside else scene.outside(r)
        e = region_evidence(r, scene, _plan_wall_share(self.toolpath, layer, r.bbox_mm), motion, outside)
        if e.near_moved_part:
            e = dataclasses.replace(e, ledge=scene.ledge(motion))
        before = _match(r, self.previous)
        if before is not None and before.area_mm2 > 0:
            e = dataclasses.replace(e, growth=float(np.log2(max(r.area_mm2, 1e-3) / before.area_mm2)))
        r.kind, r.kind_confidence = _decide(kind_scores(e, motion))
        r.displacement_mm = ((round(motion.dx_mm, 3), round(motion.dy_mm, 3))
                             if r.kind in MOVED_KINDS else None)
        r.outline_mm = ()
