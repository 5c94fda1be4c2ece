"""Where the printed part's top layer sits against its plan: translation and rotation by phase correlation.

:func:`part_motion` registers the edges of the layer's rendered reference
(its top layer only) against the edges of the photo's top view and says how
far, and whether turned, the part moved. It is the *whole-part motion*
evidence of :mod:`layerwatch.analysis.failure_typing` (a layer shift is a
pure translation, a detached part also turns) and the source of the
displacement in bed mm that a layer shift or a detachment reports.
:class:`NewMaterial` registers the same layer against the edges that are new
since the print's previous photo (series mode): at a shift's first layers the
unmoved layers below outweigh the moved layer in the whole photo, not in
what is new.

Cost (issue 18's per-layer budget)
----------------------------------
Only the footprint's bounding box widened by :data:`MOVE_MAX_MM` is
registered (the caller may pass the footprint's box, :func:`mask_box`,
found once per layer). The transforms are SciPy's single-precision real
FFTs on one thread; the photo's spectrum is computed once and reused by the
rotation search and the turned part's translation, and the peak is read in
the search window only. The correlation stays at full resolution and on
exactly the box it always used: the move decision compares peak heights
(:data:`SECOND_PEAK`), and even growing the box by a few pixels to
FFT-friendly sides (426 -> 432 px, 1.2 ms less) changed that decision on
2 photos (5 of 1582 typed regions) of the evaluation; a half-resolution
surface would change the heights more.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
import scipy.fft as sfft

from layerwatch.geometry.topview import TopView

__all__ = ["EDGE_PAD_PX", "MOVE_MAX_MM", "MOVE_MIN_MM", "ROTATION_GAIN", "ROTATION_MIN_DEG", "ROTATIONS_DEG",
           "SECOND_PEAK", "PartMotion", "edges", "mask_box", "moved_area", "NewMaterial", "crop_box", "pad_box", "part_motion",
           "self_similarity", "top_from_plan"]

#: smallest displacement of the part's top layer reported as a move, mm (registration noise is ~0.2 mm)
MOVE_MIN_MM = 0.75
#: a correlation peak away from zero shift wins over the zero-shift peak when at least this high a share of it
#: (:data:`CANDIDATE_PEAK`'s floor; 0.6 before session 11: on layers of several small objects the unmoved
#: layers' ledges, much outline per area, keep the zero-shift peak high, and the true move's peak read 0.58 of it
#: on KISSlicer; a move whose new place shows bare bed is still refused, ``failure_typing.ARRIVED_MIN``)
SECOND_PEAK = 0.5
#: rotation that tells a detached part from a layer shift (a pure translation), degrees
ROTATION_MIN_DEG = 2.5
#: ... when the best rotated reference correlates this many times better than the unrotated one
ROTATION_GAIN = 1.45
#: largest displacement searched, mm (the crop around the footprint is widened by it)
MOVE_MAX_MM = 12.0
#: a correlation peak at least this share of the zero-shift peak is a candidate for a moved layer's new place
CANDIDATE_PEAK = 0.5
#: most candidates compared (the highest)
MAX_CANDIDATES = 8
#: reference edges above this share of their 99th percentile are the plan's own (where a moved layer is not new)
PLANNED_EDGE = 0.2
#: rotations searched for a moved part, degrees
ROTATIONS_DEG = np.arange(-10.0, 10.01, 1.0)
#: most ECC iterations refining a moved part's motion
ECC_ITERATIONS = 50
#: an ECC result farther than this from the phase correlation's start is not taken, mm
ECC_MAX_STEP_MM = 1.5


@dataclass(frozen=True)
class PartMotion:
    """How far the printed part's top layer sits from where the plan puts it.

    Attributes
    ----------
    dx_mm, dy_mm : float
        Displacement of the photo's part against the reference, bed mm (of the point
        :attr:`pivot_mm`, the footprint's centroid, when the part turned).
    rotation_deg : float
        Rotation of the part about its centre, degrees (counter-clockwise in
        the top view; 0 unless the part moved: the search runs only then).
    rotation_gain : float
        Correlation peak of the best rotation over that of no rotation (1 = no evidence of a turn).
    peak : float
        Height of the chosen correlation peak (phase correlation, 0-1; higher = clearer).
    pivot_mm : tuple of float or None
        ``(x, y)`` bed mm the rotation turns about, the footprint's centroid, whose
        displacement ``(dx_mm, dy_mm)`` is; None unless the part moved.
    refined : bool
        Translation and rotation refined by ECC (:func:`_refine`); the rotation is then
        measured, not only the better of 1 degree steps.
    """

    dx_mm: float = 0.0
    dy_mm: float = 0.0
    rotation_deg: float = 0.0
    rotation_gain: float = 1.0
    peak: float = 0.0
    pivot_mm: tuple[float, float] | None = None
    refined: bool = False

    @property
    def magnitude_mm(self) -> float:
        return float(math.hypot(self.dx_mm, self.dy_mm))

    @property
    def moved(self) -> bool:
        """A move of at least :data:`MOVE_MIN_MM`."""
        return self.magnitude_mm >= MOVE_MIN_MM and self.peak > 0

    @property
    def turned(self) -> bool:
        """The part turned by :data:`ROTATION_MIN_DEG` or more, clearly (a detachment, not a shift).

        Clearly: measured by ECC (:attr:`refined`), or the best of the 1 degree
        steps correlates :data:`ROTATION_GAIN` times better than no turn.
        """
        return abs(self.rotation_deg) >= ROTATION_MIN_DEG and (self.refined or self.rotation_gain >= ROTATION_GAIN)


def edges(grey: np.ndarray) -> np.ndarray:
    """Gradient magnitude of a grey image smoothed at 1.5 px, float32 (H, W).

    A pixel's value depends on the 8 px around it only (Gaussian radius 6,
    Sobel radius 1): a crop padded by 8 px gives the whole image's values
    inside the unpadded crop.
    """
    g = cv2.GaussianBlur(np.asarray(grey, np.float32), (0, 0), 1.5)
    return cv2.magnitude(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3))


#: context an :func:`edges` value reads around its pixel, px
EDGE_PAD_PX = 8


def mask_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """Bounding box ``(v0, v1, u0, u1)`` (end exclusive, px) of the nonzero pixels of a 2-D mask; None when empty."""
    m = np.ascontiguousarray(mask)
    m = m.view(np.uint8) if m.dtype == bool else (m != 0).view(np.uint8)
    u, v, w, h = cv2.boundingRect(m)
    if w == 0 or h == 0:
        return None
    return v, v + h, u, u + w


def pad_box(box: tuple[int, int, int, int], pad_px: int, shape: tuple[int, int]) -> tuple[slice, slice]:
    """``box`` widened by ``pad_px`` on each side, clipped to an image of ``shape``, as slices."""
    v0, v1, u0, u1 = box
    return (slice(max(0, v0 - pad_px), min(shape[0], v1 + pad_px)),
            slice(max(0, u0 - pad_px), min(shape[1], u1 + pad_px)))


class _PhaseCorrelator:
    """Phase correlation (Kuglin & Hassler 1975) of images of one shape against a fixed image ``b``.

    The inputs are Hanning windowed over their own shape; ``b``'s spectrum is
    computed once (single precision, SciPy's real FFT). :meth:`surface`
    gives the correlation of ``a`` with ``b`` with zero shift at
    ``(H // 2, W // 2)``, smoothed at 1 px.
    """

    def __init__(self, b: np.ndarray) -> None:
        h, w = b.shape
        self.shape = (h, w)
        self.window = cv2.createHanningWindow((w, h), cv2.CV_32F)
        self.B = self._spectrum(b)

    def _spectrum(self, x: np.ndarray) -> np.ndarray:
        return sfft.rfft2(np.asarray(x, np.float32) * self.window, workers=1)

    def surface(self, a: np.ndarray) -> np.ndarray:
        """Correlation surface of ``b`` against ``a`` (the shape given to the constructor), float32."""
        R = self.B * np.conj(self._spectrum(a))
        R /= np.maximum(np.abs(R), 1e-12)
        r = sfft.irfft2(R, s=self.shape, workers=1)
        return cv2.GaussianBlur(np.fft.fftshift(r), (0, 0), 1.0)


def _peak(r: np.ndarray, reach_px: float, exclude_px: float = 0.0) -> tuple[float, float, float]:
    """Highest point ``(du, dv, height)`` of a correlation surface within ``reach_px`` of zero shift (sub-pixel).

    Only the square of half side ``reach_px`` about zero shift is read;
    shifts closer than ``exclude_px`` to zero are not considered. The
    sub-pixel position is the centroid of the 3 x 3 neighbourhood of the
    highest point, above its lowest value.
    """
    h, w = r.shape
    cy, cx = h // 2, w // 2
    n = int(math.floor(reach_px))
    v_lo, v_hi, u_lo, u_hi = max(cy - n, 0), min(cy + n + 1, h), max(cx - n, 0), min(cx + n + 1, w)
    yy, xx = np.ogrid[v_lo:v_hi, u_lo:u_hi]
    sub = r[v_lo:v_hi, u_lo:u_hi]
    rr = np.where(np.hypot(yy - cy, xx - cx) >= exclude_px, sub, -np.inf) if exclude_px > 0 else sub
    v, u = np.unravel_index(int(np.argmax(rr)), rr.shape)
    return _centroid(r, int(v) + v_lo, int(u) + u_lo)


def _centroid(r: np.ndarray, v: int, u: int) -> tuple[float, float, float]:
    """``(du, dv, height)`` of the point ``(v, u)`` of a correlation surface, sub-pixel (see :func:`_peak`)."""
    h, w = r.shape
    cy, cx = h // 2, w // 2
    p = r[max(v - 1, 0): v + 2, max(u - 1, 0): u + 2]
    p = p - p.min()
    vy, vx = np.mgrid[max(v - 1, 0): v + 2, max(u - 1, 0): u + 2]
    s = float(p.sum()) or 1.0
    return float((vx * p).sum() / s - cx), float((vy * p).sum() / s - cy), float(r[v, u])


def _candidates(r: np.ndarray, reach_px: float, near_px: float, floor: float) -> list[tuple[int, int]]:
    """Local maxima ``(v, u)`` of a correlation surface at least ``near_px`` and at most ``reach_px`` from zero
    shift and at least ``floor`` high, highest first, at most :data:`MAX_CANDIDATES` (5 x 5 neighbourhoods)."""
    h, w = r.shape
    cy, cx = h // 2, w // 2
    n = int(math.floor(reach_px))
    v_lo, v_hi, u_lo, u_hi = max(cy - n, 0), min(cy + n + 1, h), max(cx - n, 0), min(cx + n + 1, w)
    sub = np.ascontiguousarray(r[v_lo:v_hi, u_lo:u_hi])
    top = (sub >= cv2.dilate(sub, np.ones((5, 5), np.uint8))) & (sub >= floor)
    vv, uu = np.nonzero(top)
    vv, uu = vv + v_lo, uu + u_lo
    far = np.hypot(vv - cy, uu - cx) >= near_px
    vv, uu = vv[far], uu[far]
    order = np.argsort(-r[vv, uu], kind="stable")[:MAX_CANDIDATES]
    return [(int(vv[k]), int(uu[k])) for k in order]


def _new_edges_match(a: np.ndarray, b: np.ndarray, planned: np.ndarray, du: int, dv: int) -> float:
    """How well the layer's edges ``a`` moved by ``(du, dv)`` px match the photo's ``b`` where the plan has no edges.

    Normalised correlation over the pixels outside ``planned`` (the reference's edges at zero shift,
    widened): where the moved layer newly lies, its edges must be in the photo.
    """
    h, w = a.shape
    shift = np.array([[1.0, 0.0, du], [0.0, 1.0, dv]], np.float32)
    moved = cv2.warpAffine(a, shift, (w, h)) * ~planned
    energy = float(np.sqrt(float((moved * moved).sum())))
    return float((moved * b).sum()) / energy if energy > 0 else 0.0


def self_similarity(a: np.ndarray, du: float, dv: float) -> float:
    """How much the layer's edges look like themselves shifted by ``(du, dv)`` px, 0-1 (1 at no shift).

    Parameters
    ----------
    a : ndarray, float32, shape (h, w)
        The registered layer's edges (the reference's :func:`edges` on the top layer, seen),
        Hanning windowed here as the phase correlation windows them.
    du, dv : float
        The shift, px (x right, y down).

    Returns
    -------
    float
        The autocorrelation of the windowed ``a`` at ``(du, dv)`` over its value at no
        shift (0 for an empty ``a``). High at a multiple of a regular infill's period and
        for a layer of dense, blurred lines that overlap themselves; low for a sparse layer
        (walls, open infill) shifted off its own lines.
    """
    h, w = a.shape
    aw = np.asarray(a, np.float32) * cv2.createHanningWindow((w, h), cv2.CV_32F)
    energy = float((aw * aw).sum())
    if energy <= 0:
        return 0.0
    shift = np.array([[1.0, 0.0, du], [0.0, 1.0, dv]], np.float32)
    return float((aw * cv2.warpAffine(aw, shift, (w, h), flags=cv2.INTER_LINEAR)).sum()) / energy


def _looks_like_itself(a: np.ndarray, du: float, dv: float, share: float) -> bool:
    """A move of ``(du, dv)`` px whose peak is ``share`` (< 1) of the zero-shift peak that the layer's own pattern
    explains: the layer's edges, shifted so, match themselves at least as well (:func:`self_similarity` >= ``share``)."""
    return share < 1.0 and self_similarity(a, du, dv) >= share


def _rotation(a: np.ndarray, b: np.ndarray, centre: tuple[float, float]) -> tuple[float, float]:
    """Best rotation of ``a`` about ``centre`` (px) to match ``b``, searched at half resolution: ``(degrees, gain)``."""
    a2 = cv2.resize(a, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    b2 = cv2.resize(b, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    h, w = a2.shape
    corr = _PhaseCorrelator(b2)
    c = (centre[0] / 2, centre[1] / 2)
    heights = []
    for ang in ROTATIONS_DEG:
        turned = cv2.warpAffine(a2, cv2.getRotationMatrix2D(c, float(ang), 1.0), (w, h))
        heights.append(float(corr.surface(turned).max()))
    k = int(np.argmax(heights))
    zero = heights[int(np.argmin(np.abs(ROTATIONS_DEG)))]
    return float(ROTATIONS_DEG[k]), heights[k] / max(zero, 1e-9)


def part_motion(top: np.ndarray, reference: np.ndarray, footprint: np.ndarray, topview: TopView,
                valid: np.ndarray | None = None,
                footprint_box: tuple[int, int, int, int] | None = None,
                hints: tuple[PartMotion, ...] = (), crop_edges: dict | None = None) -> PartMotion:
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
    footprint_box : tuple of int, optional
        :func:`mask_box` of ``footprint`` when the caller has it.
    hints : tuple of PartMotion, optional
        Translations known from elsewhere (the print's layer shift seen on an earlier photo:
        a shift stays), compared with the strong peaks as the moved layer's new place
        when the part moved and did not turn (:func:`_new_place`).
    crop_edges : dict, optional
        Filled with the registered crop (``"box"``, :func:`crop_box`) and its edge images
        (``"layer"``: the top layer's reference edges, ``"top"``: the photo's, both zero where
        unseen) for :class:`NewMaterial` to reuse.

    Returns
    -------
    PartMotion
        No motion (peak 0) when there is no footprint or nothing to register.

    Notes
    -----
    Phase correlation of edge images (gradient magnitude: a rendering and a
    photo differ in shading but agree on where beads and walls are) inside
    the footprint's bounding box widened by :data:`MOVE_MAX_MM`, Hanning
    windowed. Only the
    reference's *top layer* (its footprint widened by 1 mm) is registered,
    against the whole photo crop. The lower layers, which stay where they
    were when only the top layers shifted, give a peak at zero shift: a peak
    at least :data:`MOVE_MIN_MM` away that reaches :data:`SECOND_PEAK` of it
    is taken as the top layer's move. For a moved part the reference is
    also turned in 1 degree steps about the footprint's centroid
    (:data:`ROTATIONS_DEG`): a clear gain at a large angle is a part that
    turned (a detachment). A moved part that did not turn takes as its
    translation the strong peak (the chosen one or any local maximum of at
    least :data:`CANDIDATE_PEAK` of the zero-shift peak) whose moved edges the
    photo shows best where the reference has none (:func:`_new_place`): at
    a shift's first layers the layers below give peaks within about a
    millimetre of zero that can outrank the moved layer's own.

    A move whose peak is lower than the zero-shift peak is refused when the
    layer's own edges, shifted by it, overlap themselves at least as much as
    the peak's share of the zero-shift peak (:func:`self_similarity`): a
    regular infill looks like itself a period away, and a layer of dense
    lines overlaps itself at any small shift, so a defect that weakens the
    zero-shift peak (missing infill) left such a peak to pass for a layer
    shift (Simplify3D cross-part run). The price: a real shift whose peak is
    weaker than the layers below's and whose layer is that dense is not
    measured (a straight wall moved along itself overlaps itself too).
    """
    fp = np.asarray(footprint, bool)
    fbox = mask_box(fp) if footprint_box is None else footprint_box
    if fbox is None:
        return PartMotion()
    box = pad_box(fbox, int(round(MOVE_MAX_MM * topview.px_per_mm)), fp.shape)
    seen = np.ones(fp[box].shape, bool) if valid is None else np.asarray(valid, bool)[box]
    k = int(round(topview.px_per_mm)) * 2 + 1
    top_layer = cv2.GaussianBlur(cv2.dilate(fp[box].astype(np.uint8), np.ones((k, k), np.uint8)).astype(np.float32),
                                 (0, 0), 2.0)
    ref_edges = edges(reference[box])
    a = ref_edges * top_layer * seen  # unseen pixels 0 (edge strengths are finite)
    b = edges(top[box]) * seen
    if crop_edges is not None:
        crop_edges.update(box=box, layer=a, top=b)
    h, w = a.shape
    if h < 16 or w < 16 or not a.any() or not b.any():
        return PartMotion()
    corr = _PhaseCorrelator(b)
    r = corr.surface(a)
    reach, near = MOVE_MAX_MM * topview.px_per_mm, MOVE_MIN_MM * topview.px_per_mm
    du, dv, height = _peak(r, reach)
    zero = height if math.hypot(du, dv) < near else _peak(r, near)[2]  # the zero-shift peak
    if math.hypot(du, dv) < near:
        du2, dv2, height2 = _peak(r, reach, exclude_px=near)
        if height2 >= SECOND_PEAK * height and not _looks_like_itself(a, du2, dv2, height2 / height):
            du, dv, height = du2, dv2, height2
    d = topview.to_mm(np.array([du, dv], float)) - topview.to_mm(np.zeros(2))
    if math.hypot(du, dv) < near:
        return PartMotion(float(d[0]), float(d[1]), peak=height)
    # the footprint's centroid: the point whose displacement is reported (a turned part moves each point by
    # another amount)
    v0, u0 = fbox[0] - box[0].start, fbox[2] - box[1].start
    vv, uu = np.nonzero(fp[box][v0: v0 + fbox[1] - fbox[0], u0: u0 + fbox[3] - fbox[2]])
    centre = (float(uu.mean()) + u0, float(vv.mean()) + v0)
    pivot = topview.to_mm(np.array([centre[0] + box[1].start, centre[1] + box[0].start], float))
    angle, gain = _rotation(a, b, centre)
    motion = PartMotion(float(d[0]), float(d[1]), angle, gain, height, (float(pivot[0]), float(pivot[1])))
    if motion.turned:  # the translation of the turned part: register the turned reference
        turned = cv2.warpAffine(a, cv2.getRotationMatrix2D(centre, angle, 1.0), (w, h))
        du, dv, height = _peak(corr.surface(turned), reach)
        d = topview.to_mm(np.array([du, dv], float)) - topview.to_mm(np.zeros(2))
        motion = PartMotion(float(d[0]), float(d[1]), angle, gain, height, motion.pivot_mm)
    motion = _refine(motion, a, b, centre, topview)
    if motion.turned:
        return motion
    # a part that did not turn: which of the strong peaks away from zero is the layer's new place
    du2, dv2, height2 = _new_place(r, a, b, ref_edges, (du, dv, height), reach, near,
                                   [_to_px(m, topview) for m in hints if m.moved])
    if (du2, dv2) == (du, dv):
        return motion
    if _looks_like_itself(a, du2, dv2, height2 / max(zero, 1e-12)):
        return motion
    d = topview.to_mm(np.array([du2, dv2], float)) - topview.to_mm(np.zeros(2))
    return dataclasses.replace(motion, dx_mm=float(d[0]), dy_mm=float(d[1]), peak=height2)


class NewMaterial:
    """Where the material printed since the print's previous photo lies against the layer's plan.

    :func:`part_motion` registers the layer against the whole photo, where the layers
    below (unmoved at a shift's first layers, and with much outline per area on small
    objects) give a peak at zero shift that the moved layer's own peak must reach a share
    of (:data:`SECOND_PEAK`): at the onset of a shift on KISSlicer's and Cura's plates the
    true peak read 0.27-0.45 of it. The camera is stationary: what the previous photo
    already showed (the layers below, the bed, a plate's other objects) is no new edge.
    Here the layer's reference edges (its top layer, as :func:`part_motion` forms them) are
    compared with the edges that are new in the photo (its edge strength above the previous
    photo's): on a sound print the layer printed since is new where the plan puts it, after a
    shift at the gantry's offset.

    Parameters
    ----------
    top : ndarray, uint8, shape (H, W)
        Grey top view of the photo on the layer's plane.
    previous : ndarray, uint8
        Grey top view of the print's previous photo **on the same plane** (the same warp, the
        same residual view shift undone): the whole view (H, W), or only :attr:`box`
        (:func:`crop_box` gives it before the object is made).
    reference : ndarray, uint8, shape (H, W)
        The layer's rendered reference.
    footprint : ndarray, bool, shape (H, W)
        Pixels printed in the layer (not empty).
    topview : TopView
    valid, previous_valid : ndarray, bool, optional
        Pixels the camera saw in ``top`` (H, W) and in ``previous`` (its shape).
    footprint_box : tuple of int, optional
        :func:`mask_box` of ``footprint``.
    crop_edges : dict, optional
        :func:`part_motion`'s edge images of the same crop (its ``crop_edges``), not computed again.

    Notes
    -----
    A top view of the previous photo on another plane would be off by the parallax of the
    height difference (about 2 px a layer here), which makes every edge new along one side.
    """

    def __init__(self, top: np.ndarray, previous: np.ndarray, reference: np.ndarray, footprint: np.ndarray,
                 topview: TopView, valid: np.ndarray | None = None, previous_valid: np.ndarray | None = None,
                 footprint_box: tuple[int, int, int, int] | None = None, crop_edges: dict | None = None) -> None:
        fp = np.asarray(footprint, bool)
        self.topview = topview
        self.box = crop_box(fp, topview, footprint_box)
        box = self.box
        whole = previous.shape[:2] == fp.shape
        seen = np.ones(fp[box].shape, bool) if valid is None else np.asarray(valid, bool)[box]
        if previous_valid is not None:
            seen = seen & np.asarray(previous_valid, bool)[box if whole else (slice(None), slice(None))]
        if crop_edges is not None and crop_edges.get("box") == box:  # part_motion's, zero where unseen
            layer, top_edges = crop_edges["layer"], crop_edges["top"]
        else:
            k = int(round(topview.px_per_mm)) * 2 + 1
            top_layer = cv2.GaussianBlur(cv2.dilate(fp[box].astype(np.uint8), np.ones((k, k), np.uint8))
                                         .astype(np.float32), (0, 0), 2.0)
            layer, top_edges = edges(reference[box]) * top_layer, edges(top[box])
        #: the layer's reference edges (top layer) and the photo's new edges on :attr:`box`, float32
        self.layer = layer * seen
        self.new = np.maximum(top_edges - edges(previous[box] if whole else previous), 0.0) * seen

    @cached_property
    def _surface(self) -> np.ndarray | None:
        """The phase correlation of the layer's edges against the new edges (zero shift at the centre); None when
        either image is empty."""
        a, b = self.layer, self.new
        h, w = a.shape
        if h < 16 or w < 16 or not a.any() or not b.any():
            return None
        return _PhaseCorrelator(b).surface(a)

    def motion(self) -> PartMotion:
        """The translation (bed mm) of the highest peak of the phase correlation of the layer's edges against
        the new edges, ``peak`` its height; no rotation. No motion (peak 0) when either image is empty."""
        r = self._surface
        return PartMotion() if r is None else _motion_px(_peak(r, MOVE_MAX_MM * self.topview.px_per_mm), self.topview)

    def evidence(self) -> np.ndarray | None:
        """The surface of :meth:`motion` on the displacements up to :data:`MOVE_MAX_MM` (the square of half side
        ``n``, that reach in px), over its highest point: float32 (2n + 1, 2n + 1), zero shift at the centre,
        zero where the crop is narrower; None when either image is empty.

        A layer shift stays: every photo after its onset measures the same vector again on its own new
        material, so the surfaces of a run of photos add up (:func:`evidence_motion`), and a peak that a
        single photo's layer leaves ambiguous is decided by the next ones. Each photo is one measurement:
        its surface's heights follow how much edge its layer has, so it counts relative to its own peak.
        """
        r = self._surface
        if r is None:
            return None
        n = int(math.floor(MOVE_MAX_MM * self.topview.px_per_mm))
        h, w = r.shape
        cy, cx = h // 2, w // 2
        v_lo, v_hi, u_lo, u_hi = max(cy - n, 0), min(cy + n + 1, h), max(cx - n, 0), min(cx + n + 1, w)
        out = np.zeros((2 * n + 1, 2 * n + 1), np.float32)
        out[v_lo - cy + n:v_hi - cy + n, u_lo - cx + n:u_hi - cx + n] = r[v_lo:v_hi, u_lo:u_hi]
        top = float(out.max())
        return out / top if top > 0 else None

    def placed(self, motion: PartMotion) -> bool:
        """Whether the layer was printed where ``motion`` puts it rather than where the plan does.

        ``c(d)``, the layer's edges moved by ``d`` times the new edges (summed), is ``c(0)``'s
        prediction under each explanation: printed at ``d``, the new edges are the layer's
        own moved by ``d``, so ``c(0) / c(d)`` is the layer's :func:`self_similarity` at ``d``
        (only where moved and planned edges overlap is the plan's place new too); printed as
        planned, with something else new beside it (strands, an object), ``c(0) >= c(d)``.
        The move stands when ``c(0) / c(d)`` lies below the midpoint of the two predictions.
        """
        if not motion.moved:
            return False
        a, b = self.layer, self.new
        h, w = a.shape
        du, dv = _to_px(motion, self.topview)
        moved = cv2.warpAffine(a, np.array([[1.0, 0.0, du], [0.0, 1.0, dv]], np.float32), (w, h))
        at_d, at_0 = float((moved * b).sum()), float((a * b).sum())
        if at_d <= 0:
            return False
        return at_0 / at_d < 0.5 * (1.0 + self_similarity(a, du, dv))


def evidence_motion(evidence: np.ndarray, topview: TopView) -> PartMotion:
    """The translation (bed mm) of the highest point of :meth:`NewMaterial.evidence` (or a sum of them),
    ``peak`` its height (photos agreeing there); no rotation."""
    return _motion_px(_peak(evidence, MOVE_MAX_MM * topview.px_per_mm), topview)


def _motion_px(peak: tuple[float, float, float], topview: TopView) -> PartMotion:
    """A correlation peak ``(du, dv, height)`` (top-view px) as a :class:`PartMotion` (bed mm)."""
    du, dv, height = peak
    d = topview.to_mm(np.array([du, dv], float)) - topview.to_mm(np.zeros(2))
    return PartMotion(float(d[0]), float(d[1]), peak=height)


def crop_box(footprint: np.ndarray, topview: TopView,
             footprint_box: tuple[int, int, int, int] | None = None) -> tuple[slice, slice]:
    """The registered crop: the footprint's box widened by :data:`MOVE_MAX_MM`, as slices (empty for no footprint)."""
    fp = np.asarray(footprint, bool)
    fbox = mask_box(fp) if footprint_box is None else footprint_box
    if fbox is None:
        return slice(0, 0), slice(0, 0)
    return pad_box(fbox, int(round(MOVE_MAX_MM * topview.px_per_mm)), fp.shape)


def _to_px(motion: PartMotion, topview: TopView) -> tuple[float, float]:
    """A motion's translation as ``(du, dv)`` top-view px."""
    d = topview.to_px(np.array([motion.dx_mm, motion.dy_mm])) - topview.to_px(np.zeros(2))
    return float(d[0]), float(d[1])


def _new_place(r: np.ndarray, a: np.ndarray, b: np.ndarray, ref_edges: np.ndarray,
               chosen: tuple[float, float, float], reach: float, near: float,
               hints: list[tuple[float, float]] | None = None) -> tuple[float, float, float]:
    """The move among the strong correlation peaks whose new edges the photo shows best: ``(du, dv, height)``.

    At a shift's first layers the unmoved layers below give the highest peak (zero shift) and
    peaks within about a millimetre of it (their walls and perimeters seen at an angle), often
    higher than the moved layer's own. The candidates are ``chosen`` and the local maxima at
    least :data:`CANDIDATE_PEAK` of the zero-shift peak (:func:`_candidates`); each is scored by
    :func:`_new_edges_match` outside the reference's own edges (above :data:`PLANNED_EDGE` of
    their 99th percentile, widened by 2 px): the near peaks of the layers below land
    mostly on those edges, the layer's true new place does not. ``hints`` (``(du, dv)`` px,
    e.g. the print's shift seen earlier) are candidates too, whatever their height, unless
    ``near`` or nearer to ``chosen`` or a candidate (this photo's own peak measures that move).
    """
    h, w = r.shape
    zero = _peak(r, near)[2]
    cands = _candidates(r, reach, near, CANDIDATE_PEAK * zero)
    for du, dv in hints or []:  # a hint this photo's own peaks do not already measure
        v, u = int(round(dv)) + h // 2, int(round(du)) + w // 2
        known = [(chosen[1] + h // 2, chosen[0] + w // 2), *cands]
        if 0 < v < h - 1 and 0 < u < w - 1 and min(math.hypot(v - a, u - b) for a, b in known) >= near:
            cands.append((v, u))
    strong = ref_edges[ref_edges > 0]
    if not cands or strong.size == 0:
        return chosen
    planned = cv2.dilate((ref_edges > PLANNED_EDGE * float(np.percentile(strong, 99))).view(np.uint8),
                         np.ones((5, 5), np.uint8)).astype(bool)
    best, best_score = chosen, _new_edges_match(a, b, planned, int(round(chosen[0])), int(round(chosen[1])))
    for v, u in cands:
        score = _new_edges_match(a, b, planned, u - w // 2, v - h // 2)
        if score > best_score:
            best, best_score = _centroid(r, v, u), score
    return best


def _refine(motion: PartMotion, a: np.ndarray, b: np.ndarray, centre: tuple[float, float],
            topview: TopView) -> PartMotion:
    """``motion`` refined by ECC (Evangelidis & Psarakis 2008): a rigid motion of ``a`` onto ``b``, sub-pixel.

    Starts from the phase correlation's translation and the best rotation of
    the 1 degree steps (also when its gain alone is too small to call the part
    turned) and fits rotation and translation together on the edge images of
    the crop (:data:`ECC_ITERATIONS` at most). Returns ``motion`` unchanged
    when ECC does not converge or moves the start by more than
    :data:`ECC_MAX_STEP_MM` (it locked on something else, e.g. the layers
    below a shifted layer); else the refined rotation, ``refined=True`` and,
    for a part turned by :data:`ROTATION_MIN_DEG` or more, the refined
    displacement of ``centre`` (px in the crop: the footprint's centroid). A part that did not turn keeps the phase correlation's
    translation: ECC's drifts toward the edges of the layers below a
    shifted layer, which stay at zero shift (seen on the simulator's
    layer shifts, by up to 0.9 mm).
    """
    s = topview.px_per_mm
    start = np.asarray(cv2.getRotationMatrix2D(centre, motion.rotation_deg, 1.0), np.float64)
    start[:, 2] += np.array([motion.dx_mm, -motion.dy_mm]) * s  # bed +y is image -v
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, ECC_ITERATIONS, 1e-4)
    try:
        _, warp = cv2.findTransformECC(np.asarray(a, np.float32), np.asarray(b, np.float32), start.astype(np.float32),
                                       cv2.MOTION_EUCLIDEAN, criteria)
    except cv2.error:  # did not converge: the phase correlation's answer stands
        return motion
    c = np.array([centre[0], centre[1], 1.0])
    warp = np.asarray(warp, np.float64)
    moved_px = warp @ c - np.asarray(centre)
    if np.hypot(*(moved_px - start @ c + np.asarray(centre))) > ECC_MAX_STEP_MM * s:
        return motion
    angle = math.degrees(math.atan2(float(warp[0, 1]), float(warp[0, 0])))
    if abs(angle) < ROTATION_MIN_DEG:  # not turned: ECC's translation drifts toward the layers below a shift
        return dataclasses.replace(motion, rotation_deg=angle, refined=True)
    return PartMotion(float(moved_px[0] / s), float(-moved_px[1] / s), angle, motion.rotation_gain, motion.peak,
                      motion.pivot_mm, refined=True)


def top_from_plan(motion: PartMotion, topview: TopView) -> np.ndarray:
    """The 2 x 3 affine (top-view px) that carries the planned layer to where the photo shows it, float64.

    The rotation :attr:`PartMotion.rotation_deg` about :attr:`PartMotion.pivot_mm`
    when the part :attr:`~PartMotion.turned` (as :func:`part_motion` turned the reference), then the translation ``(dx_mm, dy_mm)``; the identity for a part
    that did not move.
    """
    M = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    if not motion.moved:
        return M
    if motion.turned and motion.pivot_mm is not None:
        pivot = topview.to_px(np.asarray(motion.pivot_mm, float))
        M = cv2.getRotationMatrix2D((float(pivot[0]), float(pivot[1])), motion.rotation_deg, 1.0)
    M[:, 2] += topview.to_px(np.array([motion.dx_mm, motion.dy_mm])) - topview.to_px(np.zeros(2))
    return M


def moved_area(outline: np.ndarray, motion: PartMotion, topview: TopView) -> np.ndarray:
    """Where a moved layer is and should not be, and where it should be and is not, bool (H, W).

    Parameters
    ----------
    outline : ndarray, bool, shape (H, W)
        The layer's planned area (its footprint with the gaps of sparse infill closed).
    motion : PartMotion
    topview : TopView

    Returns
    -------
    ndarray, bool, shape (H, W)
        ``outline`` XOR ``outline`` carried by :func:`top_from_plan` (empty when the part did not move):
        the area a layer shift or a detachment shows the operator, rather than the blocks that fired at its edges.
    """
    fp = np.asarray(outline, bool)
    if not motion.moved:
        return np.zeros(fp.shape, bool)
    h, w = fp.shape
    moved = cv2.warpAffine(fp.view(np.uint8), top_from_plan(motion, topview), (w, h), flags=cv2.INTER_NEAREST)
    return moved.astype(bool) ^ fp
