"""Lower floors the empty-bed photo cannot judge: the reference's HOG on them.

The scene channel (:mod:`layerwatch.analysis.scene_change`) judges whatever
the camera sees beside the printed layer against the scene's expected
appearance ``E``. On bare bed ``E`` is the empty-bed photo; on the part's own
lower floors (the plate round a boss, the floor of a hollow box, a ledge)
``E`` is the last photo that showed them. A photo that no earlier photo of
its series preceded (single-photo mode, a monitor started mid-print, the
layers of a skipped photo) has no such photo: those *hidden ledges* lie in
the predicted change and nothing judged them, so an object lying on a lower
floor beside the top layer was invisible (single-photo foreign bodies "beside
the part" on the example part, where "beside" is the plate round the boss).

The camera-view reference renders those floors as the camera sees them
(:mod:`layerwatch.render.volume`): where the bed photo cannot be the
reference, the rendering is (issue 18: "where the camera sees bare bed, the
reference is that photo, not a rendering"). :func:`ledge_regions` takes the
layer's HOG similarities, which the comparison computes for every block,
and reports the blocks mostly on hidden ledges, outside the blocks eq. (5)
considered, that fall below T_S: as regions beside the printed layer
(``LayerResult.outside_regions``), not in a%.

A thin object of moderate contrast on a floor of fine infill lines (a hex key
on the plate round a boss) barely changes the blocks' gradient histograms;
its colour does. :func:`off_colour` is the second test on the hidden ledges:
a lower floor is the part's own filament, so in the same photo its CIELAB
chroma ``(a*, b*)`` lies on the part's *shading line*, the segment from grey
(shadow, glare, a dark or overexposed pixel lose chroma, not hue) through the
part's median chroma measured on the printed layer's footprint to 1.5 times
it (a saturated, lit face). Pixels far from that line are another material;
exposure and white balance shift the part and the floor alike, so neither
counts, and a highlight adds the light's white, which keeps the hue. Pixels
with a channel at :data:`CLIPPED` or above (and their neighbours) are not
judged: a clipped highlight turns orange into pale yellow. The test judges nothing on dark, grey, white or mixed-colour parts
(footprint chroma under :data:`MIN_PART_CHROMA`, or spread off its own line):
an object of another hue on them is left to the HOG test.

References
----------
Petsiuk & Pearce (2022), Section 2.4, eqs. (4)-(5) (the similarity and T_S);
the whole-view figure beside eq. (5) is issue 18's.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.analysis.result import Region
from layerwatch.analysis.scene_change import change_regions
from layerwatch.errors import AnalysisError
from layerwatch.geometry.topview import TopView

__all__ = ["CLIPPED", "LEDGE_SHARE", "MIN_PART_CHROMA", "OFF_CELL_SHARE", "OFF_LINE_MIN", "OFF_LINE_SHARE",
           "ON_LINE_SHARE", "ledge_blocks", "ledge_regions", "off_colour", "part_chroma"]

#: share of a block's tile that must lie on hidden ledges for the block to be judged there
LEDGE_SHARE = 0.5
#: the colour test judges a part whose median chroma |(a*, b*)| is at least this (CIELAB units)
MIN_PART_CHROMA = 12.0
#: a pixel is off-colour when its (a*, b*) lies farther from the part's shading line than
#: ``max(OFF_LINE_MIN, OFF_LINE_SHARE * chroma)`` (CIELAB units)
OFF_LINE_MIN, OFF_LINE_SHARE = 10.0, 0.3
#: share of a cell's pixels (cell_px x cell_px window) that must be off-colour for them to count
OFF_CELL_SHARE = 0.3
#: share of the footprint's pixels that must lie on the part's shading line for the part to be judged
ON_LINE_SHARE = 0.8
#: a pixel with a channel at this value or above is clipped: its colour is not judged
CLIPPED = 245


def _chroma(top_bgr: np.ndarray) -> np.ndarray:
    """CIELAB ``(a*, b*)`` of a BGR top view, float32 (H, W, 2), 0 = grey (OpenCV's 8-bit Lab, offset removed)."""
    lab = cv2.cvtColor(np.ascontiguousarray(top_bgr, np.uint8), cv2.COLOR_BGR2LAB)
    return lab[..., 1:].astype(np.float32) - 128.0


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
    img = np.asarray(top_bgr)
    fp = np.asarray(footprint, bool)
    if img.ndim != 3 or img.shape[2] != 3 or fp.shape != img.shape[:2] or np.count_nonzero(fp) < 100:
        return None
    ab = _chroma(img)[fp]
    part = np.median(ab, axis=0).astype(np.float32)
    if float(np.hypot(*part)) < MIN_PART_CHROMA:
        return None
    if float(np.mean(_off_line(ab, part) <= _line_tolerance(part))) < ON_LINE_SHARE:
        return None
    return part


def off_colour(top_bgr: np.ndarray, footprint: np.ndarray, ledges_top: np.ndarray, cell_px: int) -> np.ndarray | None:
    """Pixels of the hidden ledges whose material is not the part's filament (see module notes).

    Parameters
    ----------
    top_bgr : ndarray, uint8, shape (H, W, 3)
        Colour top view of the layer plane (BGR).
    footprint : ndarray, bool, shape (H, W)
        The printed layer's footprint, limited to what the camera saw (the part's colour).
    ledges_top : ndarray, bool, shape (H, W)
        Hidden ledges in the top view, limited to what the camera saw.
    cell_px : int
        HOG cell size, px: pixels count when at least :data:`OFF_CELL_SHARE` of the
        ``cell_px`` x ``cell_px`` window round them is off-colour.

    Returns
    -------
    ndarray, bool, shape (H, W) or None
        Off-colour ledge pixels (the ledges eroded by half a cell: their borders
        show walls and the bed beside them); None when :func:`part_chroma` cannot
        judge the part.
    """
    part = part_chroma(top_bgr, footprint)
    if part is None:
        return None
    c = max(int(cell_px), 1)
    ledges = cv2.erode(np.asarray(ledges_top, np.uint8), np.ones((c // 2 * 2 + 1,) * 2, np.uint8)) > 0
    if not ledges.any():
        return np.zeros(ledges.shape, bool)
    ys, xs = np.nonzero(ledges)
    box = (slice(max(ys.min() - c, 0), ys.max() + c + 1), slice(max(xs.min() - c, 0), xs.max() + c + 1))
    img = np.asarray(top_bgr)[box]
    clipped = cv2.dilate((img.max(axis=2) >= CLIPPED).view(np.uint8), np.ones((3, 3), np.uint8)) > 0
    off = (_off_line(_chroma(img), part) > _line_tolerance(part)) & ledges[box] & ~clipped
    share = cv2.blur(off.astype(np.float32), (c, c), borderType=cv2.BORDER_CONSTANT)
    out = np.zeros(ledges.shape, bool)
    out[box] = off & (share >= OFF_CELL_SHARE)
    return out


def ledge_blocks(ledges_top: np.ndarray, grid_shape: tuple[int, int], cell_px: int, block_cells: int) -> np.ndarray:
    """Blocks whose tile (the cell at the block's centre) lies at least :data:`LEDGE_SHARE` on the ledges.

    Parameters
    ----------
    ledges_top : ndarray, bool, shape (H, W)
        Hidden ledges in the top view of the layer plane.
    grid_shape : (N, M)
        The HOG block grid.
    cell_px, block_cells : int

    Returns
    -------
    ndarray, bool, shape (N, M)
    """
    n, m = grid_shape
    c = int(cell_px)
    off = (int(block_cells) - 1) * c // 2
    tiles = np.zeros((n * c, m * c), np.float32)
    src = np.asarray(ledges_top, np.float32)[off : off + n * c, off : off + m * c]
    tiles[: src.shape[0], : src.shape[1]] = src
    return cv2.resize(tiles, (m, n), interpolation=cv2.INTER_AREA) >= LEDGE_SHARE


def ledge_regions(heat: np.ndarray, considered: np.ndarray, ledges_top: np.ndarray, threshold: float,
                  cell_px: int, block_cells: int, topview: TopView, min_area_mm2: float,
                  off_colour_top: np.ndarray | None = None) -> list[Region]:
    """Regions of hidden-ledge blocks whose similarity with the reference is below ``threshold``.

    Parameters
    ----------
    heat : ndarray, float, shape (N, M)
        The layer's block similarities (``LayerResult.heatmap``).
    considered : ndarray, bool, shape (N, M)
        Blocks eq. (5) counted (``LayerResult.mask``): left to a%.
    ledges_top : ndarray, bool, shape (H, W)
        Hidden ledges in the top view, already limited to what the camera saw.
    threshold : float
        T_S.
    cell_px, block_cells : int
    topview : TopView
    min_area_mm2 : float
        Regions below this area (mm^2 on the layer plane) are left out.
    off_colour_top : ndarray, bool, shape (H, W), optional
        :func:`off_colour` pixels: they join the failing tiles (their similarity
        counted as ``threshold / 2``).

    Returns
    -------
    list of Region
        :func:`~layerwatch.analysis.scene_change.change_regions` of the failing
        tiles: bed mm, largest first, ``outside_fraction`` 1.

    Raises
    ------
    AnalysisError
        ``heat`` and ``considered`` differ in shape, or ``ledges_top`` (``off_colour_top``) is not the
        top view's shape.
    """
    h = np.asarray(heat)
    if (np.shape(considered) != h.shape or np.shape(ledges_top) != tuple(topview.shape)
            or (off_colour_top is not None and np.shape(off_colour_top) != tuple(topview.shape))):
        raise AnalysisError(f"similarities {h.shape}, considered blocks {np.shape(considered)} and ledges "
                            f"{np.shape(ledges_top)} do not fit a {topview.shape} top view's block grid.")
    low = ledge_blocks(ledges_top, h.shape, cell_px, block_cells) & ~np.asarray(considered, bool) & (h < threshold)
    coloured = off_colour_top is not None and bool(np.any(off_colour_top))
    if not low.any() and not coloured:
        return []
    c = int(cell_px)
    off = (int(block_cells) - 1) * c // 2
    H, W = topview.shape
    sim = np.where(low, h, 1.0).astype(np.float32)
    tiles = np.ones((H, W), np.float32)
    up = np.repeat(np.repeat(sim, c, 0), c, 1)[: H - off, : W - off]
    tiles[off : off + up.shape[0], off : off + up.shape[1]] = up
    if coloured:
        tiles = np.where(np.asarray(off_colour_top, bool), np.minimum(tiles, 0.5 * threshold), tiles)
    return change_regions(tiles < threshold, tiles, topview, min_area_mm2)
