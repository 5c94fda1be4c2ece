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
its colour does: :func:`~layerwatch.analysis.part_colour.off_colour` is the
second test on the hidden ledges (a lower floor is the part's own filament),
and its pixels join the failing tiles of :func:`ledge_regions`.

*Tops in the layer's slab.* A plate whose objects a slicer prints in turns
(KISSlicer: one object on the layers at 0.263 mm steps, the others at 0.278
mm, interleaved) has, on each layer, the other objects' last tops a fraction
of a layer below the layer plane: not printed on this layer, yet at its
height (:func:`slab_layers`, :func:`slab_tops`). The top view of the layer
plane maps them as exactly as the printed layer, after the same registration,
so they are judged as the printed layer's blocks are (the blocks with a cell
on them, the colour test eroded by half a cell), not eroded by the scene
channel's margin as a lower floor is: a 4.6 mm cube's top eroded by 1.5 mm on
each side leaves nothing to judge. Only where they are hidden (inside ``M``:
no earlier photo of the series showed them), like the ledges.

References
----------
Petsiuk & Pearce (2022), Section 2.4, eqs. (4)-(5) (the similarity and T_S);
the whole-view figure beside eq. (5) is issue 18's.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from layerwatch.analysis.block_masks import block_tiles
from layerwatch.analysis.result import Region
from layerwatch.analysis.scene_change import change_regions
from layerwatch.errors import AnalysisError
from layerwatch.gcode.toolpath import Layer
from layerwatch.geometry.topview import TopView

__all__ = ["LEDGE_SHARE", "SLAB_TOL_MM", "ledge_blocks", "ledge_regions", "slab_layers", "slab_tops"]

#: share of a block's tile that must lie on hidden ledges for the block to be judged there
LEDGE_SHARE = 0.5
#: an earlier layer's top lies in a layer's slab when it is this much above the layer's bottom, mm (the G-code's
#: z rounding: a layer printed directly below, at the bottom of the slab, is not in it)
SLAB_TOL_MM = 1e-3


def slab_layers(layers: Sequence[Layer], index: int) -> list[int]:
    """Earlier layers whose top lies inside layer ``index``'s slab (above its bottom ``z - height``).

    Parameters
    ----------
    layers : sequence of Layer
        The toolpath's layers (``Toolpath.layers``: top height ``z`` and thickness ``height``, mm), by
        ascending ``z``.
    index : int

    Returns
    -------
    list of int
        The layers ``j < index`` with ``z_j > z_index - height_index + SLAB_TOL_MM``, ascending: empty unless
        the slicer prints the plate's objects at interleaved heights (or the layer's thickness is unknown).
    """
    if index <= 0 or index >= len(layers) or not layers[index].height > 0:
        return []
    bottom = float(layers[index].z) - float(layers[index].height) + SLAB_TOL_MM
    j = index - 1
    while j >= 0 and float(layers[j].z) > bottom:
        j -= 1
    return list(range(j + 1, index))


def slab_tops(earlier: Sequence[np.ndarray], footprint: np.ndarray) -> np.ndarray:
    """The tops of :func:`slab_layers` that the layer does not print over, bool (H, W).

    Parameters
    ----------
    earlier : sequence of ndarray, bool, shape (H, W)
        The slab layers' top-view footprints.
    footprint : ndarray, bool, shape (H, W)
        The layer's own footprint.

    Raises
    ------
    AnalysisError
        A footprint is not ``footprint``'s shape.
    """
    fp = np.asarray(footprint, bool)
    out = np.zeros(fp.shape, bool)
    for f in earlier:
        if np.shape(f) != fp.shape:
            raise AnalysisError(f"footprint {np.shape(f)} of a slab layer is not the layer's {fp.shape}.")
        out |= np.asarray(f, bool)
    return out & ~fp


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
                  off_colour_top: np.ndarray | None = None, judged: np.ndarray | None = None) -> list[Region]:
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
        :func:`~layerwatch.analysis.part_colour.off_colour` pixels: they join the failing tiles (their similarity
        counted as ``threshold / 2``).
    judged : ndarray, bool, shape (N, M), optional
        Blocks judged besides those on the ledges (the blocks with a cell on the hidden tops of the layer's
        slab, :func:`slab_tops`).

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
            or (off_colour_top is not None and np.shape(off_colour_top) != tuple(topview.shape))
            or (judged is not None and np.shape(judged) != h.shape)):
        raise AnalysisError(f"similarities {h.shape}, considered blocks {np.shape(considered)} and ledges "
                            f"{np.shape(ledges_top)} do not fit a {topview.shape} top view's block grid.")
    on = ledge_blocks(ledges_top, h.shape, cell_px, block_cells)
    if judged is not None:
        on |= np.asarray(judged, bool)
    low = on & ~np.asarray(considered, bool) & (h < threshold)
    coloured = off_colour_top is not None and bool(np.any(off_colour_top))
    if not low.any() and not coloured:
        return []
    c = int(cell_px)
    H, W = topview.shape
    sim = np.where(low, h, 1.0).astype(np.float32)
    tiles = block_tiles(sim, (H, W), c, int(block_cells), fill=1.0)
    if coloured:
        tiles = np.where(np.asarray(off_colour_top, bool), np.minimum(tiles, 0.5 * threshold), tiles)
    return change_regions(tiles < threshold, tiles, topview, min_area_mm2)
