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

References
----------
Petsiuk & Pearce (2022), Section 2.4, eqs. (4)-(5) (the similarity and T_S);
the whole-view figure beside eq. (5) is issue 18's.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.analysis.block_masks import block_tiles
from layerwatch.analysis.result import Region
from layerwatch.analysis.scene_change import change_regions
from layerwatch.errors import AnalysisError
from layerwatch.geometry.topview import TopView

__all__ = ["LEDGE_SHARE", "ledge_blocks", "ledge_regions"]

#: share of a block's tile that must lie on hidden ledges for the block to be judged there
LEDGE_SHARE = 0.5


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
        :func:`~layerwatch.analysis.part_colour.off_colour` pixels: they join the failing tiles (their similarity
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
    H, W = topview.shape
    sim = np.where(low, h, 1.0).astype(np.float32)
    tiles = block_tiles(sim, (H, W), c, int(block_cells), fill=1.0)
    if coloured:
        tiles = np.where(np.asarray(off_colour_top, bool), np.minimum(tiles, 0.5 * threshold), tiles)
    return change_regions(tiles < threshold, tiles, topview, min_area_mm2)
