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
  neighbourhood, then a rotation search. A part whose top layer sits at
  least :data:`MOVE_MIN_MM` away from where the plan puts it has moved: a
  *layer shift* (the gantry skipped steps: a pure translation) or, when it
  also turned by :data:`ROTATION_MIN_DEG` or more, a *detachment* (a part
  knocked loose turns as it slides). Regions within the moved part's reach
  take that kind and the displacement.
* **Where**: the share of the region outside the part's closed outline
  (the footprint with the gaps of sparse infill closed; material where the
  plan has none: strands, objects, a moved part) against inside (material
  missing or disturbed where the plan prints). The scene channel's regions
  beside the printed layer count as outside.
* **Colour**: how far the region's material (its pixels unlike the bare
  bed) lies from the printed part's colour (median CIELAB distance,
  lightness half weighted against shading). A foreign body is another
  material; strands and a pit in the infill are the part's own filament.
* **Texture**: mean edge strength of the photo against the reference in the
  region; beside the part (where the reference is bare bed) many thin
  edges are strands. Inside the part it is no evidence: a pit shows the
  layers below, as many edges as strands on the part.
* **Plan under it**: the share of wall segments (perimeters) against infill
  segments of the layer's G-code inside the region: a gap in a wall is a
  *thin-wall* defect, one in the infill an *infill defect*.
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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from layerwatch.analysis.failure_kinds import UNKNOWN
from layerwatch.analysis.result import LayerResult, Region
from layerwatch.gcode.toolpath import FEATURES, Toolpath
from layerwatch.geometry.topview import TopView

__all__ = ["MOVE_MIN_MM", "ROTATION_MIN_DEG", "FailureTyper", "PartMotion", "RegionEvidence", "kind_scores",
           "part_motion", "region_evidence"]

#: smallest displacement of the part's top layer reported as a move, mm (registration noise is ~0.2 mm)
MOVE_MIN_MM = 0.75
#: a correlation peak away from zero shift wins over the zero-shift peak when at least this high a share of it
SECOND_PEAK = 0.6
#: rotation that tells a detached part from a layer shift (a pure translation), degrees
ROTATION_MIN_DEG = 2.5
#: ... when the best rotated reference correlates this many times better than the unrotated one
ROTATION_GAIN = 1.45
#: largest displacement searched, mm (the crop around the footprint is widened by it)
MOVE_MAX_MM = 12.0
#: rotations searched for a moved part, degrees
ROTATIONS_DEG = np.arange(-10.0, 10.01, 1.0)
#: CIELAB distance (lightness half weighted) above which a pixel is unlike a reference colour
COLOUR_DELTA = 22.0
#: median CIELAB distance of a region's material from the part: 0 (the part's filament) to 1 (another material)
PART_DELTA = (20.0, 40.0)

_WALL = tuple(FEATURES.index(n) for n in ("perimeter", "external_perimeter"))
_INFILL = tuple(FEATURES.index(n) for n in ("infill", "solid_infill", "top_solid_infill", "bridge"))


@dataclass(frozen=True)
class PartMotion:
    """How far the printed part's top layer sits from where the plan puts it.

    Attributes
    ----------
    dx_mm, dy_mm : float
        Translation of the photo's part against the reference, bed mm.
    rotation_deg : float
        Rotation of the part about its centre, degrees (counter-clockwise in
        the top view; 0 unless the part moved: the search runs only then).
    rotation_gain : float
        Correlation peak of the best rotation over that of no rotation (1 = no evidence of a turn).
    peak : float
        Height of the chosen correlation peak (phase correlation, 0-1; higher = clearer).
    """

    dx_mm: float = 0.0
    dy_mm: float = 0.0
    rotation_deg: float = 0.0
    rotation_gain: float = 1.0
    peak: float = 0.0

    @property
    def magnitude_mm(self) -> float:
        return float(math.hypot(self.dx_mm, self.dy_mm))

    @property
    def moved(self) -> bool:
        """A move of at least :data:`MOVE_MIN_MM`."""
        return self.magnitude_mm >= MOVE_MIN_MM and self.peak > 0

    @property
    def turned(self) -> bool:
        """The part turned by :data:`ROTATION_MIN_DEG` or more, clearly (a detachment, not a shift)."""
        return abs(self.rotation_deg) >= ROTATION_MIN_DEG and self.rotation_gain >= ROTATION_GAIN


def _edges(grey: np.ndarray) -> np.ndarray:
    """Gradient magnitude of a grey image smoothed at 1.5 px, float32 (H, W)."""
    g = cv2.GaussianBlur(np.asarray(grey, np.float32), (0, 0), 1.5)
    return cv2.magnitude(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3))


def _crop(mask: np.ndarray, pad_px: int) -> tuple[slice, slice] | None:
    vv, uu = np.nonzero(mask)
    if vv.size == 0:
        return None
    h, w = mask.shape
    return (slice(max(0, vv.min() - pad_px), min(h, vv.max() + pad_px + 1)),
            slice(max(0, uu.min() - pad_px), min(w, uu.max() + pad_px + 1)))


def _correlation(a: np.ndarray, b: np.ndarray, window: np.ndarray) -> np.ndarray:
    """Phase-correlation surface of ``b`` against ``a`` (same shape), zero shift at the centre, float32."""
    A = np.fft.rfft2(a * window)
    B = np.fft.rfft2(b * window)
    R = B * np.conj(A)
    R /= np.maximum(np.abs(R), 1e-12)
    r = np.fft.fftshift(np.fft.irfft2(R, s=a.shape)).astype(np.float32)
    return cv2.GaussianBlur(r, (0, 0), 1.0)


def _peak(r: np.ndarray, reach_px: float, exclude_px: float = 0.0) -> tuple[float, float, float]:
    """Highest point ``(du, dv, height)`` of a correlation surface within ``reach_px`` of zero shift (sub-pixel).

    Shifts closer than ``exclude_px`` to zero are not considered.
    """
    h, w = r.shape
    cy, cx = h // 2, w // 2
    yy, xx = np.ogrid[:h, :w]
    dist = np.maximum(np.abs(yy - cy), np.abs(xx - cx))
    rr = np.where((dist <= reach_px) & (np.hypot(yy - cy, xx - cx) >= exclude_px), r, -np.inf)
    v, u = np.unravel_index(int(np.argmax(rr)), rr.shape)
    p = r[max(v - 1, 0): v + 2, max(u - 1, 0): u + 2]
    p = p - p.min()
    vy, vx = np.mgrid[max(v - 1, 0): v + 2, max(u - 1, 0): u + 2]
    s = float(p.sum()) or 1.0
    return float((vx * p).sum() / s - cx), float((vy * p).sum() / s - cy), float(r[v, u])


def _rotation(a: np.ndarray, b: np.ndarray, centre: tuple[float, float]) -> tuple[float, float]:
    """Best rotation of ``a`` about ``centre`` (px) to match ``b``, searched at half resolution: ``(degrees, gain)``."""
    a2 = cv2.resize(a, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    b2 = cv2.resize(b, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    h, w = a2.shape
    window = cv2.createHanningWindow((w, h), cv2.CV_32F)
    c = (centre[0] / 2, centre[1] / 2)
    heights = []
    for ang in ROTATIONS_DEG:
        turned = cv2.warpAffine(a2, cv2.getRotationMatrix2D(c, float(ang), 1.0), (w, h))
        heights.append(float(_correlation(turned, b2, window).max()))
    k = int(np.argmax(heights))
    zero = heights[int(np.argmin(np.abs(ROTATIONS_DEG)))]
    return float(ROTATIONS_DEG[k]), heights[k] / max(zero, 1e-9)


def part_motion(top: np.ndarray, reference: np.ndarray, footprint: np.ndarray, topview: TopView,
                valid: np.ndarray | None = None) -> PartMotion:
    """Register the printed part's top layer in the top view against its reference: translation (mm) and rotation.

    Parameters
    ----------
    top : ndarray, uint8, shape (H, W)
        Grey top view of the photo on the layer's plane.
    reference : ndarray, uint8, shape (H, W)
        The layer's rendered reference (same view).
    footprint : ndarray, bool, shape (H, W)
        Pixels printed in the layer.
    topview : TopView
    valid : ndarray, bool, shape (H, W), optional
        Pixels the camera saw (others do not count).

    Returns
    -------
    PartMotion
        No motion (peak 0) when there is no footprint or nothing to register.

    Notes
    -----
    Phase correlation (Kuglin & Hassler 1975) of edge images (gradient
    magnitude: a rendering and a photo differ in shading but agree on where
    beads and walls are) inside the footprint's bounding box widened by
    :data:`MOVE_MAX_MM`, Hanning windowed. Only the reference's *top layer*
    (its footprint widened by 1 mm) is registered, against the whole photo
    crop. The lower layers, which stay where they were when only the top
    layers shifted, give a peak at zero shift: a peak at least
    :data:`MOVE_MIN_MM` away that reaches :data:`SECOND_PEAK` of it is taken
    as the top layer's move. For a moved part the reference is also turned
    in 1 degree steps about the footprint's centre (:data:`ROTATIONS_DEG`):
    a clear gain at a large angle is a part that turned (a detachment).
    """
    fp = np.asarray(footprint, bool)
    box = _crop(fp, int(round(MOVE_MAX_MM * topview.px_per_mm)))
    if box is None:
        return PartMotion()
    seen = np.ones(fp[box].shape, bool) if valid is None else np.asarray(valid, bool)[box]
    k = int(round(topview.px_per_mm)) * 2 + 1
    top_layer = cv2.GaussianBlur(cv2.dilate(fp[box].astype(np.uint8), np.ones((k, k), np.uint8)).astype(np.float32),
                                 (0, 0), 2.0)
    a = np.where(seen, _edges(reference[box]) * top_layer, 0).astype(np.float32)
    b = np.where(seen, _edges(top[box]), 0).astype(np.float32)
    h, w = a.shape
    if h < 16 or w < 16 or not a.any() or not b.any():
        return PartMotion()
    r = _correlation(a, b, cv2.createHanningWindow((w, h), cv2.CV_32F))
    reach, near = MOVE_MAX_MM * topview.px_per_mm, MOVE_MIN_MM * topview.px_per_mm
    du, dv, height = _peak(r, reach)
    if math.hypot(du, dv) < near:
        du2, dv2, height2 = _peak(r, reach, exclude_px=near)
        if height2 >= SECOND_PEAK * height:
            du, dv, height = du2, dv2, height2
    d = topview.to_mm(np.array([du, dv], float)) - topview.to_mm(np.zeros(2))
    if math.hypot(du, dv) < near:
        return PartMotion(float(d[0]), float(d[1]), peak=height)
    vv, uu = np.nonzero(fp[box])
    centre = (float(uu.mean()), float(vv.mean()))
    angle, gain = _rotation(a, b, centre)
    motion = PartMotion(float(d[0]), float(d[1]), angle, gain, height)
    if motion.turned:  # the translation of the turned part: register the turned reference
        turned = cv2.warpAffine(a, cv2.getRotationMatrix2D(centre, angle, 1.0), (w, h))
        du, dv, height = _peak(_correlation(turned, b, cv2.createHanningWindow((w, h), cv2.CV_32F)), reach)
        d = topview.to_mm(np.array([du, dv], float)) - topview.to_mm(np.zeros(2))
        motion = PartMotion(float(d[0]), float(d[1]), angle, gain, height)
    return motion


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
    """

    outside: float
    foreign: float
    texture: float
    wall: float
    growth: float = float("nan")
    near_moved_part: bool = False


def _lab(top_bgr: np.ndarray) -> np.ndarray:
    img = np.asarray(top_bgr, np.uint8)
    bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img
    lab = cv2.cvtColor(bgr, cv2.COLOR_BGR2LAB).astype(np.float32)
    lab[..., 0] *= 100.0 / 255.0  # L in 0-100, a/b offset by 128 (differences only)
    return lab


def _unlike(lab: np.ndarray, colour: np.ndarray) -> np.ndarray:
    d = lab - colour
    return np.sqrt((0.5 * d[..., 0]) ** 2 + d[..., 1] ** 2 + d[..., 2] ** 2) > COLOUR_DELTA


class _Scene:
    """Per-photo quantities every region's evidence reads (computed once per typed layer)."""

    def __init__(self, top_bgr: np.ndarray, top: np.ndarray, reference: np.ndarray, footprint: np.ndarray,
                 topview: TopView, valid: np.ndarray | None) -> None:
        self.topview = topview
        self.fp = np.asarray(footprint, bool)
        self.valid = np.ones(self.fp.shape, bool) if valid is None else np.asarray(valid, bool)
        self.lab = _lab(top_bgr)
        k = max(3, int(round(2.0 * topview.px_per_mm)) | 1)
        inner = cv2.erode(self.fp.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool) & self.valid
        far = ~cv2.dilate(self.fp.astype(np.uint8), np.ones((4 * k, 4 * k), np.uint8)).astype(bool) & self.valid
        self.part_colour = np.median(self.lab[inner if inner.sum() > 50 else self.fp & self.valid], axis=0) \
            if (self.fp & self.valid).any() else None
        self.bed_colour = np.median(self.lab[far], axis=0) if far.sum() > 50 else None
        self.top_e, self.ref_e = _edges(top), _edges(reference)
        # the part's outline with the gaps of sparse infill and holes closed: "inside the part"
        k2 = max(3, int(round(3.0 * topview.px_per_mm)) | 1)
        closed = cv2.morphologyEx(self.fp.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((k2, k2), np.uint8))
        self.solid = ndimage.binary_fill_holes(closed.astype(bool))

    def outside(self, r: Region) -> float:
        """Share of the region's box (seen pixels) outside the part's closed outline."""
        box = self.box(r)
        if box is None:
            return float(r.outside_fraction)
        seen = self.valid[box]
        return float((~self.solid[box] & seen).sum() / max(int(seen.sum()), 1))

    def box(self, r: Region) -> tuple[slice, slice] | None:
        (u0, v0), (u1, v1) = np.round(self.topview.to_px(np.array([r.bbox_mm[:2], r.bbox_mm[2:]], float))).astype(int)
        h, w = self.fp.shape
        us, vs = sorted((u0, u1)), sorted((v0, v1))
        u_lo, u_hi, v_lo, v_hi = max(0, us[0]), min(w, us[1] + 1), max(0, vs[0]), min(h, vs[1] + 1)
        if u_hi <= u_lo or v_hi <= v_lo:
            return None
        return slice(v_lo, v_hi), slice(u_lo, u_hi)


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
    """How unlike the printed part the region's material is, 0-1 (:data:`PART_DELTA` ramp of the median CIELAB distance).

    The material is the pixels unlike the bare bed when they are at least
    5 % of the region (a few strands over the bed), else all its pixels (an
    object the colour of the bed).
    """
    if scene.part_colour is None or len(lab) == 0:
        return 0.0
    if scene.bed_colour is not None:
        material = _unlike(lab, scene.bed_colour)
        if material.mean() >= 0.05:
            lab = lab[material]
    d = lab - scene.part_colour
    dist = float(np.median(np.sqrt((0.5 * d[:, 0]) ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)))
    lo, hi = PART_DELTA
    return float(np.clip((dist - lo) / (hi - lo), 0.0, 1.0))


def region_evidence(r: Region, scene: _Scene, wall: float, motion: PartMotion, outside: float) -> RegionEvidence:
    """Measure a region's evidence (module notes) in the photo of ``scene``."""
    box = scene.box(r)
    foreign, texture = 0.0, 0.0
    if box is not None:
        seen = scene.valid[box]
        if seen.any():
            foreign = _unlike_part(scene.lab[box][seen], scene)
            texture = float(np.log2((scene.top_e[box][seen].mean() + 1.0) / (scene.ref_e[box][seen].mean() + 1.0)))
    near = False
    if motion.moved:
        reach_mm = motion.magnitude_mm + 3.0
        fp_box = _crop(scene.fp, int(round(reach_mm * scene.topview.px_per_mm)))
        if fp_box is not None and box is not None:
            near = (box[0].start < fp_box[0].stop and fp_box[0].start < box[0].stop
                    and box[1].start < fp_box[1].stop and fp_box[1].start < box[1].stop)
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
    turned = 1.0 if motion.turned else -1.0
    inside = 1.0 - e.outside
    # edges count for strands beside the part only: a pit in the part also shows more edges (the layers below)
    return {
        "spaghetti": e.outside * (1.0 + edges) + 0.5 * edges + grew - 2.0 * e.foreign,
        "foreign_body": e.outside + 3.0 * e.foreign - max(grew, 0.0),
        "detachment": moved + (0.75 * turned if moved else 0.0),
        "layer_shift": moved - (0.75 * turned if moved else 0.0),
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

    def __init__(self, toolpath: Toolpath | None, topview: TopView) -> None:
        self.toolpath = toolpath
        self.topview = topview
        self.previous: list[Region] = []

    def reset(self) -> None:
        """A new print: forget the previous photo's regions."""
        self.previous = []

    def type_result(self, res: LayerResult, top_bgr: np.ndarray, top: np.ndarray, reference: np.ndarray,
                    footprint: np.ndarray, valid: np.ndarray | None = None) -> PartMotion | None:
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
            motion = part_motion(top, reference, footprint, self.topview, valid)
            scene = _Scene(top_bgr, top, reference, footprint, self.topview, valid)
        except (cv2.error, ValueError, IndexError) as exc:  # odd images: the regions stay reported, untyped
            for r in regions:
                r.kind, r.kind_confidence, r.displacement_mm = UNKNOWN, 0.0, None
            note = f"failure typing skipped ({type(exc).__name__})"
            res.message = f"{res.message}; {note}" if res.message else note
            self.previous = regions
            return None
        for r in regions:
            outside = 1.0 if any(r is q for q in res.outside_regions) else scene.outside(r)
            e = region_evidence(r, scene, _plan_wall_share(self.toolpath, res.layer, r.bbox_mm), motion, outside)
            before = _match(r, self.previous)
            if before is not None and before.area_mm2 > 0:
                e = RegionEvidence(e.outside, e.foreign, e.texture, e.wall,
                                   float(np.log2(max(r.area_mm2, 1e-3) / before.area_mm2)), e.near_moved_part)
            r.kind, r.kind_confidence = _decide(kind_scores(e, motion))
            r.displacement_mm = ((round(motion.dx_mm, 3), round(motion.dy_mm, 3))
                                 if r.kind in ("layer_shift", "detachment") else None)
        self.previous = regions
        return motion
