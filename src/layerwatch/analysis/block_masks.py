"""Blocks and pixels: per-block values painted onto an image, and the two fixes masks of blocks need.

Several checks decide per block (HOG blocks of :mod:`layerwatch.analysis.scoring`,
the change blocks of :mod:`layerwatch.analysis.scene_change`) and report per
pixel. Two layouts occur:

* square blocks of ``block_px`` from the image's corner
  (:func:`blocks_to_pixels`: the scene channel, the bed check, the first layer);
* the HOG grid, where block ``(i, j)`` spans ``block_cells`` cells of
  ``cell_px`` and *owns* the one-cell tile at its centre
  (:func:`block_tiles`; :func:`whole_blocks` paints the whole block instead).

:func:`close_gaps` and :func:`fill_holes` are the morphology such masks (and
footprints) get: gaps of sparse infill closed, the inside of an outline filled;
:func:`components` labels a mask's connected areas on its bounding box only;
:func:`touching` keeps the areas that hold seeds (a pocket open to the side, the
part's pieces that reach the layer, an object's pieces in its box).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["block_tiles", "blocks_to_pixels", "close_gaps", "components", "fill_holes", "touching", "whole_blocks"]


def blocks_to_pixels(values: np.ndarray, block_px: int, shape: tuple[int, int], fill=0) -> np.ndarray:
    """Per-block values on the pixels of square blocks laid from the image's corner, (H, W).

    Parameters
    ----------
    values : ndarray, shape (n, m)
        One value per block; block ``(i, j)`` covers rows ``[i * block_px, (i + 1) * block_px)``
        and the same columns.
    block_px : int
        Block side, px.
    shape : (H, W)
        The image's shape, px: blocks beyond it are cut off.
    fill : scalar
        Value of the pixels no block covers (right and bottom of the last blocks).

    Returns
    -------
    ndarray, shape (H, W), dtype of ``values``
    """
    v = np.asarray(values)
    b = int(block_px)
    h, w = int(shape[0]), int(shape[1])
    out = np.full((h, w), fill, dtype=v.dtype)
    hh, ww = min(h, v.shape[0] * b), min(w, v.shape[1] * b)
    out[:hh, :ww] = np.repeat(np.repeat(v[: -(-hh // b), : -(-ww // b)], b, 0), b, 1)[:hh, :ww]
    return out


def block_tiles(values: np.ndarray, shape: tuple[int, ...], cell_px: int, block_cells: int, fill=0) -> np.ndarray:
    """Paint per-block values of the HOG grid onto their tiles in an (H, W) image.

    Block ``(i, j)`` owns the ``cell_px`` square centred on the block (see
    :mod:`layerwatch.analysis.scoring`); pixels outside every tile get ``fill``.

    Parameters
    ----------
    values : ndarray, shape (N, M)
    shape : (H, W)
    cell_px, block_cells : int

    Returns
    -------
    ndarray, shape (H, W), dtype of ``values``
    """
    off = (block_cells - 1) * cell_px // 2
    out = np.full(shape, fill, dtype=values.dtype)
    tiles = np.repeat(np.repeat(values, cell_px, axis=0), cell_px, axis=1)
    h = min(shape[0] - off, tiles.shape[0])
    w = min(shape[1] - off, tiles.shape[1])
    out[off : off + h, off : off + w] = tiles[:h, :w]
    return out


def whole_blocks(blocks: np.ndarray, shape: tuple[int, int], cell_px: int, block_cells: int) -> np.ndarray:
    """The pixels of the True HOG blocks, each whole (``block_cells`` cells a side), not only its tile; bool (H, W).

    Parameters
    ----------
    blocks : ndarray, bool, shape (N, M)
    shape : (H, W)
    cell_px, block_cells : int
        The grid (:class:`~layerwatch.analysis.result.BlockGrid`).
    """
    tiles = np.asarray(block_tiles(np.asarray(blocks, bool), (int(shape[0]), int(shape[1])), cell_px, block_cells,
                                   fill=False), np.uint8)
    off = (block_cells - 1) * cell_px // 2
    if off > 0 and tiles.any():
        return cv2.dilate(tiles, np.ones((2 * off + 1, 2 * off + 1), np.uint8)) > 0
    return tiles > 0


def close_gaps(mask: np.ndarray, side_px: int) -> np.ndarray:
    """``mask`` closed (dilated, then eroded) by a ``side_px`` square: gaps narrower than it are filled; bool (H, W).

    The image's border does not erode (OpenCV's default border for the closing).
    """
    k = max(1, int(side_px))
    m = np.ascontiguousarray(mask).astype(np.uint8)
    return cv2.morphologyEx(m, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8)) > 0


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with its holes filled, bool (H, W): the background not 4-connected to the image border becomes set.

    The same as :func:`scipy.ndimage.binary_fill_holes` with its default
    structure, by one flood fill of the background from a one-pixel frame
    around the image.
    """
    m = (np.asarray(mask) != 0).astype(np.uint8)
    framed = cv2.copyMakeBorder(m, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    cv2.floodFill(framed, None, (0, 0), 2, flags=4)
    return framed[1:-1, 1:-1] != 2


def components(mask: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, tuple[int, int]]:
    """8-connected areas of ``mask``, labelled on its bounding box only.

    :func:`cv2.connectedComponentsWithStats` with its statistics costs ~2 ms on a
    600 x 600 top view however few pixels are set; a failure's regions cover a
    small part of it. The box starts on an even row and column, so that the
    labelling's 2 x 2 blocks fall as on the whole image and every area gets
    the label, and the statistics, that the whole image gives it (tested).

    Parameters
    ----------
    mask : ndarray, bool or uint8, shape (H, W)

    Returns
    -------
    n : int
        Number of labels, the background (0) included.
    labels : ndarray, int32, shape (h, w)
        Labels of the box's pixels (the whole image's ``labels[rows, cols]``).
    stats : ndarray, int32, shape (n, 5)
        ``CC_STAT_LEFT``, ``TOP``, ``WIDTH``, ``HEIGHT``, ``AREA`` per label, in whole-image
        px (row 0, the background, counts the box's background only).
    origin : (int, int)
        Row and column of the box's first pixel.
    """
    m = np.ascontiguousarray(mask)
    m = m.view(np.uint8) if m.dtype == bool else (m != 0).astype(np.uint8)
    u, v, w, h = cv2.boundingRect(m)
    if w == 0 or h == 0:
        return 1, np.zeros((0, 0), np.int32), np.array([[0, 0, m.shape[1], m.shape[0], m.size]], np.int32), (0, 0)
    v0, u0 = v & ~1, u & ~1
    n, labels, stats, _ = cv2.connectedComponentsWithStats(np.ascontiguousarray(m[v0 : v + h, u0 : u + w]),
                                                            connectivity=8)
    stats[1:, cv2.CC_STAT_LEFT] += u0
    stats[1:, cv2.CC_STAT_TOP] += v0
    return n, labels, stats, (v0, u0)


def touching(mask: np.ndarray, seeds: np.ndarray, connectivity: int = 8, min_seeds: int = 1) -> np.ndarray:
    """The connected areas of ``mask`` that hold at least ``min_seeds`` seed pixels, bool (H, W).

    A seed counts where ``mask`` is set too (a seed outside it belongs to no
    area). The areas are labelled on the mask's bounding box only (an area
    lies inside it whole, so the box gives the whole image's areas), and no
    labelling is done when no seed lies on the mask.

    Parameters
    ----------
    mask : ndarray, bool or numeric (non-zero: set), shape (H, W)
    seeds : ndarray, bool or numeric (non-zero: set), shape (H, W)
    connectivity : {4, 8}
        Neighbours that join two pixels into one area: the 4 sharing a side, or the 8 sharing a side or a corner.
    min_seeds : int
        Seed pixels an area must hold to be kept, >= 1.

    Returns
    -------
    ndarray, bool, shape (H, W)
        The kept areas' pixels (a subset of ``mask``).

    Raises
    ------
    ValueError
        When ``mask`` is not 2-D, ``seeds`` has another shape, ``connectivity`` is not 4 or 8,
        or ``min_seeds`` is below 1.
    """
    m, s = np.asarray(mask), np.asarray(seeds)
    if m.ndim != 2 or s.shape != m.shape:
        raise ValueError(f"touching: mask and seeds must be 2-D of one shape, got {m.shape} and {s.shape}")
    if connectivity not in (4, 8):
        raise ValueError(f"touching: connectivity must be 4 or 8, got {connectivity!r}")
    if int(min_seeds) != min_seeds or min_seeds < 1:
        raise ValueError(f"touching: min_seeds must be an integer >= 1, got {min_seeds!r}")
    m = np.ascontiguousarray(m.view(np.uint8) if m.dtype == bool else (m != 0).astype(np.uint8))
    out = np.zeros(m.shape, bool)
    u, v, w, h = cv2.boundingRect(m)
    box = (slice(v, v + h), slice(u, u + w))
    on = (s[box] if s.dtype == bool else s[box] != 0) & m[box].view(bool)  # the seeds on the mask
    if not on.any():
        return out
    count, labels = cv2.connectedComponents(np.ascontiguousarray(m[box]), connectivity=connectivity)
    kept = np.bincount(labels[on], minlength=count) >= int(min_seeds)  # the background counts no seed: dropped
    out[box] = kept[labels]
    return out
