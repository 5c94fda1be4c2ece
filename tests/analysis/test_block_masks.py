"""Blocks and pixels (analysis/block_masks.py) against plain loops and SciPy."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from layerwatch.analysis.block_masks import (
    block_tiles,
    blocks_to_pixels,
    close_gaps,
    components,
    fill_holes,
    touching,
    whole_blocks,
)


@pytest.mark.parametrize(("shape", "block_px"), [((40, 56), 8), ((37, 50), 8), ((20, 20), 6), ((9, 70), 4)])
def test_blocks_to_pixels_paints_each_block_from_the_corner_and_fills_the_rest(shape, block_px):
    rng = np.random.default_rng(block_px)
    n, m = -(-shape[0] // block_px) - 1, -(-shape[1] // block_px) + 1  # fewer rows, more columns than fit
    values = rng.random((n, m)).astype(np.float32)
    out = blocks_to_pixels(values, block_px, shape, fill=1.5)
    want = np.full(shape, 1.5, np.float32)
    for i in range(n):
        for j in range(m):
            want[i * block_px: (i + 1) * block_px, j * block_px: (j + 1) * block_px] = values[i, j]
    assert out.shape == shape and out.dtype == np.float32
    assert np.array_equal(out, want)
    assert np.array_equal(blocks_to_pixels(values > 0.5, block_px, shape, fill=False), (want > 0.5) & (want != 1.5))


@pytest.mark.parametrize(("cell_px", "block_cells"), [(8, 2), (6, 3), (5, 1)])
def test_whole_blocks_paints_each_true_block_whole_and_block_tiles_only_its_centre_tile(cell_px, block_cells):
    rng = np.random.default_rng(cell_px)
    shape = (70, 90)
    n = (shape[0] - (block_cells - 1) * cell_px) // cell_px
    m = (shape[1] - (block_cells - 1) * cell_px) // cell_px
    blocks = rng.random((n, m)) < 0.15
    side = block_cells * cell_px
    off = (block_cells - 1) * cell_px // 2
    whole, tiles = np.zeros(shape, bool), np.zeros(shape, bool)
    for i, j in zip(*np.nonzero(blocks), strict=True):
        whole[i * cell_px: i * cell_px + side, j * cell_px: j * cell_px + side] = True
        tiles[off + i * cell_px: off + (i + 1) * cell_px, off + j * cell_px: off + (j + 1) * cell_px] = True
    assert np.array_equal(whole_blocks(blocks, shape, cell_px, block_cells), whole)
    assert np.array_equal(block_tiles(blocks, shape, cell_px, block_cells, fill=False), tiles)
    assert not whole_blocks(np.zeros_like(blocks), shape, cell_px, block_cells).any()


def test_close_gaps_fills_gaps_narrower_than_its_square_only():
    m = np.zeros((40, 60), bool)
    m[10:30, 5:20] = m[10:30, 24:40] = True  # a 4 px gap
    m[10:30, 50:54] = True  # 10 px from the second bar, 6 px from the border
    closed = close_gaps(m, 5)
    assert closed[10:30, 20:24].all() and not closed[10:30, 40:50].any()
    assert np.array_equal(closed & ~m, np.pad(np.ones((20, 4), bool), ((10, 10), (20, 36))))
    assert np.array_equal(close_gaps(m, 1), m)


def test_fill_holes_is_scipys_binary_fill_holes():
    rng = np.random.default_rng(0)
    for _ in range(100):
        m = rng.random((int(rng.integers(1, 40)), int(rng.integers(1, 40)))) < rng.uniform(0.2, 0.8)
        assert np.array_equal(fill_holes(m), ndimage.binary_fill_holes(m))


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("threads", [1, 2])
def test_components_on_the_box_label_and_measure_every_area_as_the_whole_image_does(seed, threads):
    rng = np.random.default_rng(seed)
    mask = np.zeros((120, 150), bool)
    for _ in range(int(rng.integers(1, 25))):  # rectangles with holes, some touching: areas of any shape
        y, x = rng.integers(3, 110, 2)
        h, w = rng.integers(1, 9, 2)
        mask[y:y + h, x:x + w] = True
    mask &= rng.random(mask.shape) < 0.8
    before = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    try:
        n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
        n2, lab2, stats2, (v0, u0) = components(mask)
    finally:
        cv2.setNumThreads(before)
    assert v0 % 2 == 0 and u0 % 2 == 0
    assert n2 == n and np.array_equal(stats2[1:], stats[1:])
    rows, cols = slice(v0, v0 + lab2.shape[0]), slice(u0, u0 + lab2.shape[1])
    assert np.array_equal(lab2, lab[rows, cols])
    outside = np.ones(mask.shape, bool)
    outside[rows, cols] = False
    assert not mask[outside].any()


def test_components_of_an_empty_mask_are_the_background_alone():
    n, lab, stats, origin = components(np.zeros((10, 12), bool))
    assert n == 1 and lab.size == 0 and origin == (0, 0)
    assert stats.shape == (1, 5) and stats[0, cv2.CC_STAT_AREA] == 120


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("connectivity", [4, 8])
@pytest.mark.parametrize("min_seeds", [1, 3])
def test_touching_keeps_the_areas_holding_enough_seeds_as_scipys_labels_count_them(seed, connectivity, min_seeds):
    rng = np.random.default_rng(seed)
    mask = np.zeros((90, 110), bool)
    mask[5:80, 7:100] = rng.random((75, 93)) < 0.45  # many small areas, some joined by corners only; a margin
    seeds = rng.random(mask.shape) < 0.05  # on and off the mask
    structure = np.ones((3, 3), bool) if connectivity == 8 else ndimage.generate_binary_structure(2, 1)
    labels, n = ndimage.label(mask, structure=structure)
    want = np.zeros(mask.shape, bool)
    for k in range(1, n + 1):
        area = labels == k
        if np.count_nonzero(area & seeds) >= min_seeds:
            want |= area
    assert 0 < np.count_nonzero(want) < np.count_nonzero(mask)  # some areas kept, some not
    got = touching(mask, seeds, connectivity=connectivity, min_seeds=min_seeds)
    assert got.dtype == bool and np.array_equal(got, want)
    assert np.array_equal(touching(mask.astype(np.uint8) * 255, seeds.astype(np.float32), connectivity, min_seeds), want)


def test_touching_joins_pixels_that_share_a_corner_only_at_connectivity_8():
    mask = np.zeros((6, 6), bool)
    mask[1:3, 1:3] = mask[3:5, 3:5] = True  # two squares meeting at a corner
    seeds = np.zeros_like(mask)
    seeds[1, 1] = True
    assert np.array_equal(touching(mask, seeds, connectivity=8), mask)
    only_first = np.zeros_like(mask)
    only_first[1:3, 1:3] = True
    assert np.array_equal(touching(mask, seeds, connectivity=4), only_first)


def test_touching_counts_the_seeds_on_each_area_against_min_seeds():
    mask = np.zeros((5, 12), bool)
    mask[1:4, 1:5] = mask[1:4, 7:11] = True
    seeds = np.zeros_like(mask)
    seeds[2, 1:3] = True  # two on the first area
    seeds[2, 7:10] = True  # three on the second
    seeds[0, :] = True  # off the mask: no area's
    second = np.zeros_like(mask)
    second[1:4, 7:11] = True
    assert np.array_equal(touching(mask, seeds, min_seeds=2), mask)
    assert np.array_equal(touching(mask, seeds, min_seeds=3), second)
    assert not touching(mask, seeds, min_seeds=4).any()
    assert not touching(mask, ~mask).any()  # seeds beside an area are not in it
    assert not touching(np.zeros_like(mask), seeds).any()


@pytest.mark.parametrize(("mask", "seeds", "kwargs"), [
    (np.zeros((4, 5), bool), np.zeros((5, 4), bool), {}),
    (np.zeros((2, 4, 5), bool), np.zeros((2, 4, 5), bool), {}),
    (np.zeros((4, 5), bool), np.zeros((4, 5), bool), {"connectivity": 6}),
    (np.zeros((4, 5), bool), np.zeros((4, 5), bool), {"min_seeds": 0}),
    (np.zeros((4, 5), bool), np.zeros((4, 5), bool), {"min_seeds": 1.5}),
])
def test_touching_refuses_masks_of_other_shapes_and_bad_options(mask, seeds, kwargs):
    with pytest.raises(ValueError, match="touching"):
        touching(mask, seeds, **kwargs)
