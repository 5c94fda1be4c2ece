"""The part's colour: material on the part that is not its filament.

The HOG comparison (eqs. 4-5) judges the *shape* of the gradients, so an
object lying on the part whose edges and texture have the part's scale (a
thin hex key across infill lines, a screw along a perimeter) can pass it;
its colour does not. Everything the camera sees of the part is the part's
own filament, so in the same photo its CIELAB chroma ``(a*, b*)`` lies on
the part's *shading line*: the segment from grey (shadow, glare, a dark or
overexposed pixel lose chroma, not hue) through the part's median chroma,
measured on the printed layer's footprint, to 1.5 times it (a saturated, lit
face). Pixels far from that line are another material.

Shade loses colour fidelity: the tolerance round the line widens with a
pixel's darkness against the part's median lightness, up to
:data:`DARK_WIDEN` times for black (the inside of a cavity in Blender Cycles
photos of the bundled part: dark, tinted 15-25 degrees off the part's hue by
the bed's and the faces' bounced light and the sensor's noise, was taken as
another material on 20-23 blocks of a clean layer; a dark tool of another hue
is still off).

The test is normalised by the photo itself: exposure and white balance
shift the part and the object on it alike (the part's median chroma moves
with them), so neither counts, and a highlight adds the light's white, which
keeps the hue. Pixels with a channel at :data:`CLIPPED` or above (and their
neighbours) are not judged: a clipped highlight turns orange into pale
yellow. A part whose colour cannot be told from grey (dark, grey, white
filament: footprint chroma under :data:`MIN_PART_CHROMA`) or that is not
one colour (less than :data:`ON_LINE_SHARE` of its footprint on its own
line: a multi-colour print, a translucent part showing the bed through it)
is not judged at all; an object of another hue on it is left to the HOG
test. So is a grey or black object on a coloured part (a dark lump, a
steel screw lie on the shading line): those differ in brightness, which
the HOG test sees.

Three places use it:

* :func:`off_colour`, the pixels of a mask (the *hidden ledges*,
  :mod:`layerwatch.analysis.ledges`: the lower floors no earlier photo
  showed) that are another material;
* :func:`off_colour_blocks`, the HOG blocks of the *printed layer* (its
  footprint and the part's own gaps, a sparse infill's cells) whose tile is
  at least :data:`OFF_TILE_SHARE` another material (``[analysis] off_colour``, on in the
  recommended settings, off in the paper's): the pipeline counts them as
  anomalous blocks of eq. (5) (:func:`~layerwatch.analysis.scoring.analyze_layer`).
  It works at half the top view's resolution on the footprint's bounding
  box (a 1 mm hex key is still 3 px wide at 6.67 px/mm): 0.8 ms median per
  layer of the example part at 1080p (600 x 600 px top view; CPU time on one
  thread of a loaded machine, ``benchmarks/bench_part_colour.py``);
* :func:`rim_material`, grey material at the printed layer's *rim*: the
  band :data:`RIM_MM` round the footprint's edge that neither test above
  judges (the hue test erodes the footprint by half a cell) and that the
  scene channel leaves out as the part's walls. An object lying on the
  part's edge mostly hangs over it (a screw on a perimeter: 17 % of it on
  the footprint, 6 % on the eroded one). Its pixels join the change beside
  the printed layer (the pipeline's outside regions).

Grey material. A grey or metal object (a steel screw) lies on the shading
line: its chroma is near zero, like a shadow's. What tells the two apart is
the chroma *at that lightness*: a diffuse surface in shadow keeps its chroma
in proportion to its lightness (``C* / (L* + 16)`` about constant, 0.47 for
an orange part), a grey object has almost none (0.05 for the screw at L*
62). :func:`rim_material` counts a pixel as grey material when its chroma is
under a third of what the part would have at that lightness (at least
:data:`GREY_CHROMA` below; measured from the bare bed's chroma when the bed is
grey, whose chroma is then the photo's white-balance cast), when it is lighter than the bare bed by
the factor :data:`BED_RATIO` (the bed beside the part, its shadows, the skirt's gap
are no object), no lighter than the part's median (brightest channel; a reflection of the lamp
on a glossy bed or part is brighter than any lit diffuse surface, and may
not clip) and not clipped. A metal object's own highlights are left out
with the glare: what counts is its body, lit like the part. A
part whose colour cannot be told from grey is not judged; nor is a grey
object darker than the bed, or one on a bed as light as it (left to the HOG
test).

References
----------
Petsiuk & Pearce (2022), Section 2.4 (the HOG comparison this complements); issue 18.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.analysis.scoring import printed_weight
from layerwatch.errors import AnalysisError

__all__ = ["BED_RATIO", "CLIPPED", "GREY_CHROMA", "MIN_PART_CHROMA", "OFF_CELL_SHARE", "OFF_LINE_MIN",
           "OFF_LINE_SHARE", "OFF_TILE_SHARE", "ON_LINE_SHARE", "RIM_MM", "off_colour", "off_colour_blocks",
           "part_chroma", "rim_material"]

#: the colour test judges a part whose median chroma |(a*, b*)| is at least this (CIELAB units)
MIN_PART_CHROMA = 12.0
#: a pixel is off-colour when its (a*, b*) lies farther from the part's shading line than
#: ``max(OFF_LINE_MIN, OFF_LINE_SHARE * chroma)`` (CIELAB units)
OFF_LINE_MIN, OFF_LINE_SHARE = 10.0, 0.3
#: how much wider the shading line's tolerance is for a black pixel than for one as light as the part
#: (linear in between; :func:`_off_part_line`)
DARK_WIDEN = 1.0
#: share of a cell's pixels (cell_px x cell_px window) that must be off-colour for them to count
OFF_CELL_SHARE = 0.3
#: share of a block's tile (the cell at its centre) that must be off-colour for the block to count
OFF_TILE_SHARE = 0.25
#: share of the footprint's pixels that must lie on the part's shading line for the part to be judged
ON_LINE_SHARE = 0.8
#: a pixel with a channel at this value or above is clipped: its colour is not judged
CLIPPED = 245
#: width of the rim beyond the footprint's edge that :func:`rim_material` judges, mm
RIM_MM = 4.0
#: grey material has chroma under ``max(GREY_CHROMA, part chroma at its lightness / 3)`` (CIELAB units)
GREY_CHROMA = 8.0
#: grey material is lighter than the bare bed's median by at least this factor (brightest 8-bit channel: a ratio
#: of gamma-encoded values does not change with the exposure)
BED_RATIO = 1.3
#: the bare bed is what the camera sees this far (mm) or farther from the footprint
BED_AWAY_MM = 3.0


def _lab(top_bgr: np.ndarray) -> np.ndarray:
    """OpenCV's 8-bit CIELAB of a BGR image, uint8 (H, W, 3) (``a*``, ``b*`` offset by 128)."""
    return cv2.cvtColor(np.ascontiguousarray(top_bgr, np.uint8), cv2.COLOR_BGR2LAB)


def _median_u8(values: np.ndarray) -> float:
    """The lower median of uint8 values (k,), by their histogram (linear time; k > 0)."""
    cum = np.cumsum(np.bincount(values, minlength=256))
    return float(np.searchsorted(cum, (int(cum[-1]) + 1) // 2))


def _off_line(ab: np.ndarray, part: np.ndarray) -> np.ndarray:
    """Distance of chroma ``ab`` (..., 2) from the segment ``[0, 1.5 part]`` of the (a*, b*) plane, float32 (...)."""
    c = float(np.hypot(*part))
    u = np.asarray(part, np.float32) / c
    along = ab[..., 0] * u[0] + ab[..., 1] * u[1]
    across = np.abs(ab[..., 0] * u[1] - ab[..., 1] * u[0])
    beyond = np.where(along < 0, along, np.maximum(along - 1.5 * c, 0.0))
    return np.hypot(beyond, across).astype(np.float32)


def _line_tolerance(part: np.ndarray) -> float:
    return max(OFF_LINE_MIN, OFF_LINE_SHARE * float(np.hypot(*part)))


def _off_part_line(lab: np.ndarray, dist: np.ndarray, part: np.ndarray, part_lightness: float) -> np.ndarray:
    """Pixels whose chroma lies off the part's shading line by more than the tolerance at their lightness.

    The tolerance (:func:`_line_tolerance`) holds for the part as lit; it widens by up to
    :data:`DARK_WIDEN` times as a pixel gets darker than the part's median lightness (``1 - L / L_part``,
    from 0 as lit to 1 at black): in shade and in a cavity the colour drifts (light bounced between the
    part's own faces turns an orange part red, the ambient's and the bed's colour add, the sensor's noise
    and black level weigh more). A lit object of another hue stays off (the hue test as before); a dark one
    is off when its hue is far from the part's.

    ``lab`` (h, w, 3) uint8 CIELAB; ``dist`` (h, w) float32: :func:`_off_line`; ``part``: the part's
    median chroma; ``part_lightness``: its median L (8-bit). Returns bool (h, w).
    """
    tol = np.float32(_line_tolerance(part))
    dark = np.clip(np.float32(1.0) - lab[..., 0].astype(np.float32) / np.float32(max(part_lightness, 1.0)), 0.0, 1.0)
    return dist > tol * (np.float32(1.0) + np.float32(DARK_WIDEN) * dark)


def _part(lab: np.ndarray, footprint: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The part's median chroma over ``footprint`` of ``lab`` (uint8 (h, w, 3)), each pixel's distance from
    its shading line, float32 (h, w), and the part's median lightness (8-bit L); None when the part cannot
    be judged (:func:`part_chroma`)."""
    if np.count_nonzero(footprint) < 100:
        return None
    part = np.array([_median_u8(lab[..., 1][footprint]), _median_u8(lab[..., 2][footprint])], np.float32) - 128.0
    if float(np.hypot(*part)) < MIN_PART_CHROMA:
        return None
    dist = _off_line(lab[..., 1:].astype(np.float32) - 128.0, part)
    if np.count_nonzero(dist[footprint] <= _line_tolerance(part)) < ON_LINE_SHARE * np.count_nonzero(footprint):
        return None
    return part, dist, _median_u8(lab[..., 0][footprint])


def part_chroma(top_bgr: np.ndarray, footprint: np.ndarray) -> np.ndarray | None:
    """The printed part's median chroma in this photo, or None when the colour test cannot judge it.

    Parameters
    ----------
    top_bgr : ndarray, uint8, shape (H, W, 3)
        Colour top view of the layer plane (BGR).
    footprint : ndarray, bool, shape (H, W)
        The printed layer's footprint, limited to what the camera saw.

    Returns
    -------
    ndarray, float32, shape (2,) or None
        Median ``(a*, b*)`` over the footprint; None for a grey top view, fewer than
        100 footprint pixels, a median chroma under :data:`MIN_PART_CHROMA` (dark,
        grey, white filament) or less than :data:`ON_LINE_SHARE` of the footprint on
        its own shading line (a multi-colour or patterned part).
    """
    got = _part_of(top_bgr, footprint)
    return None if got is None else got[1][0]


def _part_of(top_bgr: np.ndarray, footprint: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, float]] | None:
    """The CIELAB of ``top_bgr`` and :func:`_part` of it over ``footprint``; None as :func:`part_chroma`."""
    img = np.asarray(top_bgr)
    fp = np.asarray(footprint, bool)
    if img.ndim != 3 or img.shape[2] != 3 or fp.shape != img.shape[:2]:
        return None
    lab = _lab(img)
    got = _part(lab, fp)
    return None if got is None else (lab, got)


def _off_pixels(img: np.ndarray, off_line: np.ndarray, judged: np.ndarray, cell_px: int) -> np.ndarray:
    """Judged pixels off the part's shading line, not clipped, in cells at least :data:`OFF_CELL_SHARE` off.

    ``img`` (h, w, 3) uint8 BGR; ``off_line`` (h, w) bool: off the part's line; ``judged`` (h, w) bool;
    ``cell_px``: the window of the cell share, px of ``img``.
    """
    below = cv2.inRange(img, (0, 0, 0), (CLIPPED - 1,) * 3)  # 255 where no channel is clipped
    unclipped = cv2.erode(below, np.ones((3, 3), np.uint8)) > 0
    off = off_line & judged & unclipped
    c = max(int(cell_px), 1)
    share = cv2.blur(off.view(np.uint8).astype(np.float32), (c, c), borderType=cv2.BORDER_CONSTANT)
    return off & (share >= OFF_CELL_SHARE)


def off_colour(top_bgr: np.ndarray, footprint: np.ndarray, judged: np.ndarray, cell_px: int) -> np.ndarray | None:
    """Pixels of ``judged`` whose material is not the part's filament (see module notes).

    Parameters
    ----------
    top_bgr : ndarray, uint8, shape (H, W, 3)
        Colour top view of the layer plane (BGR).
    footprint : ndarray, bool, shape (H, W)
        The printed layer's footprint, limited to what the camera saw (the part's colour).
    judged : ndarray, bool, shape (H, W)
        Where to look (the hidden ledges), limited to what the camera saw.
    cell_px : int
        HOG cell size, px: pixels count when at least :data:`OFF_CELL_SHARE` of the
        ``cell_px`` x ``cell_px`` window round them is off-colour.

    Returns
    -------
    ndarray, bool, shape (H, W) or None
        Off-colour pixels of ``judged`` eroded by half a cell (its borders show walls and
        the bed beside them); None when :func:`part_chroma` cannot judge the part.
    """
    got = _part_of(top_bgr, footprint)
    if got is None:
        return None
    lab, (part, dist, lightness) = got
    c = max(int(cell_px), 1)
    inner = cv2.erode(np.asarray(judged, np.uint8), np.ones((c // 2 * 2 + 1,) * 2, np.uint8)) > 0
    if not inner.any():
        return np.zeros(inner.shape, bool)
    ys, xs = np.nonzero(inner)
    box = (slice(max(ys.min() - c, 0), ys.max() + c + 1), slice(max(xs.min() - c, 0), xs.max() + c + 1))
    img = np.asarray(top_bgr)[box]
    out = np.zeros(inner.shape, bool)
    out[box] = _off_pixels(img, _off_part_line(lab[box], dist[box], part, lightness), inner[box], c)
    return out


def _colour_inputs(top_bgr: np.ndarray, footprint: np.ndarray, valid: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    """The colour top view, footprint and valid mask of :func:`off_colour_blocks` and :func:`rim_material`, checked.

    Returns ``(img, footprint, valid)`` (uint8 (H, W, 3), bool (H, W), bool (H, W) or None), or None when
    the top view is not a 3-channel colour image (nothing to judge).

    Raises
    ------
    AnalysisError
        The footprint or valid mask is not the top view's shape.
    """
    img = np.asarray(top_bgr)
    if img.ndim != 3 or img.shape[2] != 3:
        return None
    shape = img.shape[:2]
    fp = np.asarray(footprint, bool)
    seen = None if valid is None else np.asarray(valid, bool)
    if fp.shape != shape or (seen is not None and seen.shape != shape):
        raise AnalysisError(f"footprint {fp.shape} and valid mask {None if seen is None else seen.shape} "
                            f"must be the top view's shape {shape}.")
    return img, fp, seen


def off_colour_blocks(top_bgr: np.ndarray, footprint: np.ndarray, valid: np.ndarray | None,
                      cell_px: int, block_cells: int, px_per_mm: float) -> np.ndarray | None:
    """HOG blocks of the printed layer whose tile is at least :data:`OFF_TILE_SHARE` another material.

    The footprint (what the camera saw of it) gives the part's colour. Judged are the footprint eroded
    by half a cell (its edge shows the wall and what lies beside it) and the tiles inside the part: the
    footprint's own gaps up to :data:`~layerwatch.analysis.scoring.PART_GAP_MM` closed, as eq. (5)'s
    ``anomalous_area = "printed"`` takes them (:func:`~layerwatch.analysis.scoring.printed_weight`: a
    sparse-infill layer's cells show the layers below, the same filament). The test runs at half the top
    view's resolution (cells of ``cell_px / 2``) on the footprint's bounding box when the cell and the
    blocks' offset are even, else at full resolution.

    Parameters
    ----------
    top_bgr : ndarray, uint8, shape (H, W, 3)
        Colour top view of the layer plane (BGR), as warped.
    footprint : ndarray, bool, shape (H, W)
        The layer's printed pixels.
    valid : ndarray, bool, shape (H, W) or None
        Pixels the camera saw (None: all).
    cell_px, block_cells : int
        The HOG cell side (px) and block side (cells).
    px_per_mm : float
        The top view's scale (the gaps closed are up to ``PART_GAP_MM`` wide).

    Returns
    -------
    ndarray, bool, shape (N, M) or None
        The block grid of the HOG (``N = H // cell_px - block_cells + 1``, likewise ``M``);
        None when the part cannot be judged (:func:`part_chroma`: grey photo, dark, grey,
        white or multi-colour part, too little of it seen).

    Raises
    ------
    AnalysisError
        The footprint or valid mask is not the top view's shape.
    """
    got_in = _colour_inputs(top_bgr, footprint, valid)
    if got_in is None:
        return None
    img, fp, seen_mask = got_in
    shape = img.shape[:2]
    seen = fp if seen_mask is None else fp & seen_mask
    c, b = int(cell_px), int(block_cells)
    n, m = shape[0] // c - b + 1, shape[1] // c - b + 1
    x, y, w, h = cv2.boundingRect(seen.view(np.uint8))
    if w == 0 or n <= 0 or m <= 0:
        return None
    f = 2 if c % 2 == 0 and ((b - 1) * c // 2) % 2 == 0 else 1
    # the box grown by a cell, its corners on the decimation's grid
    y0, x0 = max(y - c, 0) // f * f, max(x - c, 0) // f * f
    y1, x1 = min(y + h + c, shape[0]) // f * f, min(x + w + c, shape[1]) // f * f
    crop, seen_c = img[y0:y1, x0:x1], seen[y0:y1:f, x0:x1:f]
    if f > 1:
        crop = cv2.resize(crop, (seen_c.shape[1], seen_c.shape[0]), interpolation=cv2.INTER_AREA)
    lab = _lab(crop)
    got = _part(lab, seen_c)
    if got is None:
        return None
    part, dist, lightness = got
    cf = max(c // f, 1)
    inner = cv2.erode(seen_c.view(np.uint8), np.ones((cf // 2 * 2 + 1,) * 2, np.uint8)) > 0
    # the tiles inside the part (gaps of the footprint closed), on the decimated top view
    canvas = np.zeros((shape[0] // f, shape[1] // f), bool)
    canvas[y0 // f: y0 // f + seen_c.shape[0], x0 // f: x0 // f + seen_c.shape[1]] = seen_c
    lo = (b - 1) * c // 2 // f  # where the first block's tile starts
    inside = printed_weight(_tile_shares(canvas, lo, (n, m), cf), c / float(px_per_mm)) >= 1.0
    canvas[:] = False
    canvas[lo: lo + n * cf, lo: lo + m * cf] = cv2.resize(inside.view(np.uint8), (m * cf, n * cf),
                                                          interpolation=cv2.INTER_NEAREST) > 0
    judged = inner | canvas[y0 // f: y0 // f + inner.shape[0], x0 // f: x0 // f + inner.shape[1]]
    if seen_mask is not None:
        judged &= seen_mask[y0:y1:f, x0:x1:f]
    off = np.zeros((shape[0] // f, shape[1] // f), bool)
    off[y0 // f: y0 // f + inner.shape[0], x0 // f: x0 // f + inner.shape[1]] = _off_pixels(
        crop, _off_part_line(lab, dist, part, lightness), judged, cf)
    if not off.any():
        return np.zeros((n, m), bool)
    return _tile_shares(off, lo, (n, m), cf) >= OFF_TILE_SHARE


def _tile_shares(mask: np.ndarray, lo: int, grid_shape: tuple[int, int], cell: int) -> np.ndarray:
    """Share of each block's tile (``cell`` px squares from ``lo``, px) that ``mask`` (bool) covers, float32
    ``grid_shape``: :func:`~layerwatch.analysis.scoring.tile_share` by one area resize."""
    n, m = grid_shape
    tiles = np.ascontiguousarray(mask[lo: lo + n * cell, lo: lo + m * cell]).view(np.uint8).astype(np.float32)
    return cv2.resize(tiles, (m, n), interpolation=cv2.INTER_AREA)


def rim_material(top_bgr: np.ndarray, footprint: np.ndarray, valid: np.ndarray | None, cell_px: int,
                 px_per_mm: float) -> np.ndarray | None:
    """Grey material at the printed layer's rim: an object lying on the part's edge (see module notes).

    Runs at half the top view's resolution (a 1 mm object is still 3 px wide at 6.67 px/mm) on the
    footprint's box grown by the rim and the bed's distance; colours are measured only where they are used.

    Parameters
    ----------
    top_bgr : ndarray, uint8, shape (H, W, 3)
        Colour top view of the layer plane (BGR), as warped.
    footprint : ndarray, bool, shape (H, W)
        The layer's printed pixels.
    valid : ndarray, bool, shape (H, W) or None
        Pixels the camera saw (None: all).
    cell_px : int
        HOG cell side, px: the rim starts half a cell inside the footprint's edge (where the hue
        test of :func:`off_colour_blocks` stops).
    px_per_mm : float
        The top view's scale.

    Returns
    -------
    ndarray, bool, shape (H, W) or None
        Grey-material pixels of the rim (opened by a 3 x 3 square at half resolution: specks are noise);
        None when the part cannot be judged (:func:`part_chroma`), or the camera saw fewer than 100 px
        (half resolution) of bare bed.

    Raises
    ------
    AnalysisError
        The footprint or valid mask is not the top view's shape.
    """
    got_in = _colour_inputs(top_bgr, footprint, valid)
    if got_in is None:
        return None
    img, fp, seen = got_in
    shape = img.shape[:2]
    fp_seen = fp if seen is None else fp & seen
    x, y, w, h = cv2.boundingRect(fp_seen.view(np.uint8))
    if w == 0:
        return None
    f = 2
    reach = int(round(max(RIM_MM, BED_AWAY_MM) * px_per_mm)) * 2 + f
    y0, x0 = max(y - reach, 0) // f * f, max(x - reach, 0) // f * f
    y1, x1 = min(y + h + reach, shape[0]) // f * f, min(x + w + reach, shape[1]) // f * f
    crop = cv2.resize(img[y0:y1, x0:x1], ((x1 - x0) // f, (y1 - y0) // f), interpolation=cv2.INTER_AREA)
    fp_c = fp_seen[y0:y1:f, x0:x1:f]
    seen_c = np.ones(fp_c.shape, bool) if seen is None else seen[y0:y1:f, x0:x1:f]
    if np.count_nonzero(fp_c) < 100:
        return None
    mm_out = cv2.distanceTransform((~fp_c).view(np.uint8), cv2.DIST_L2, 3) * (f / float(px_per_mm))
    # the brightest channel, 8-bit: a grey's value, a coloured surface's lit channel (element-wise: numpy's
    # reduction over a 3-long axis is slow)
    value = np.maximum(np.maximum(crop[..., 0], crop[..., 1]), crop[..., 2])
    bed = seen_c & (mm_out > BED_AWAY_MM) & (value > 0)
    if np.count_nonzero(bed) < 100:
        return None
    # CIELAB only of the pixels used, as (N, 1, 3) images: every other footprint and bed pixel of the half-
    # resolution crop for the medians (the same statistics), the rim's candidates for the test
    on_part = _lab(crop[::2, ::2][fp_c[::2, ::2]][:, None, :])[:, 0]
    if len(on_part) < 25:
        return None
    part = np.array([_median_u8(on_part[:, 1]), _median_u8(on_part[:, 2])], np.float32) - 128.0
    chroma_part = float(np.hypot(*part))  # the part's colour as :func:`part_chroma` judges it
    if chroma_part < MIN_PART_CHROMA:
        return None
    if np.count_nonzero(_off_line(on_part[:, 1:].astype(np.float32) - 128.0, part) <= _line_tolerance(part)) \
            < ON_LINE_SHARE * len(on_part):
        return None
    bed_v, part_v = _median_u8(value[bed]), _median_u8(value[fp_c])
    cf = max(int(cell_px) // f, 1)
    rim = (mm_out <= RIM_MM) & seen_c & (value >= BED_RATIO * bed_v) & (value <= part_v) & (value < CLIPPED)
    rim &= ~(cv2.erode(fp_c.view(np.uint8), np.ones((cf // 2 * 2 + 1,) * 2, np.uint8)) > 0)
    ys, xs = np.nonzero(rim)
    if len(ys) == 0:
        return np.zeros(shape, bool)
    on_bed = _lab(crop[::2, ::2][bed[::2, ::2]][:, None, :])[:, 0]
    part_l = _median_u8(on_part[:, 0]) * (100.0 / 255.0)
    # a grey bed's own chroma is the photo's white-balance cast: grey is measured from it
    neutral = np.array([_median_u8(on_bed[:, 1]), _median_u8(on_bed[:, 2])], np.float32)
    if float(np.hypot(*(neutral - 128.0))) >= GREY_CHROMA:  # a coloured bed (gold PEI, blue tape): no cast known
        neutral[:] = 128.0
    px = _lab(crop[ys, xs][:, None, :])[:, 0].astype(np.float32)
    chroma = np.hypot(px[:, 1] - neutral[0], px[:, 2] - neutral[1])
    expected = chroma_part * (px[:, 0] * (100.0 / 255.0) + 16.0) / (part_l + 16.0)  # the part's at that lightness
    grey = np.zeros(fp_c.shape, np.uint8)
    grey[ys, xs] = chroma < np.maximum(GREY_CHROMA, expected / 3.0)
    grey = cv2.morphologyEx(grey, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    out = np.zeros(shape, bool)
    if not grey.any():
        return out
    out[y0:y1, x0:x1] = cv2.resize(grey, (x1 - x0, y1 - y0), interpolation=cv2.INTER_NEAREST) > 0
    return out
