"""analysis/area_reduce: OpenCV's INTER_AREA values, bit for bit, on every input the farm reduces by 3."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.analysis.area_reduce import _reduce3, area_resize
from layerwatch.analysis.frame_quality import compact_previous
from layerwatch.analysis.scene_change import to_working, working_crop


def _opencv(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def _every_sum(cn: int, seed: int) -> np.ndarray:
    """A (3, 3 n, cn) image whose n 3 x 3 blocks (per channel) sum to every value 0..2295, shuffled within."""
    rng = np.random.default_rng(seed)
    sums = np.arange(9 * 255 + 1)
    chans = []
    for c in range(cn):
        order = rng.permutation(sums) if c else sums
        blocks = np.empty((sums.size, 9), np.uint8)
        for i, s in enumerate(order):
            q, r = divmod(int(s), 9)
            b = np.full(9, q)
            b[:r] += 1
            blocks[i] = rng.permutation(b)
        chans.append(blocks.reshape(-1, 3, 3).transpose(1, 0, 2).reshape(3, -1))
    return np.stack(chans, -1) if cn > 1 else chans[0]


@pytest.mark.parametrize("cn", [1, 3])
@pytest.mark.parametrize("seed", [0, 1])
def test_every_block_sum_is_opencvs(cn: int, seed: int) -> None:
    img = _every_sum(cn, seed)
    size = (img.shape[1] // 3, 1)
    out = area_resize(img, size)
    assert out.dtype == np.uint8 and out.shape == _opencv(img, size).shape
    assert np.array_equal(out, _opencv(img, size))


def test_the_kernel_does_the_reduction() -> None:
    """The fast path is taken (not OpenCV's) on the farm's inputs: the kernel's own output is OpenCV's."""
    img = _every_sum(3, 2)
    out = np.empty((1, img.shape[1] * 3 // 3), np.uint8)
    _reduce3(img.reshape(3, -1), 3, out)
    assert np.array_equal(out.reshape(1, -1, 3), _opencv(img, (img.shape[1] // 3, 1)))


@pytest.mark.parametrize("shape", [(1080, 1920), (1080, 1920, 3), (3, 3), (3, 3, 3), (9, 6, 3), (27, 300), (723, 1242, 3)])
def test_random_frames(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(sum(shape))
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    size = (shape[1] // 3, shape[0] // 3)
    assert np.array_equal(area_resize(img, size), _opencv(img, size))


def test_extremes_and_smooth_images() -> None:
    for value in (0, 1, 4, 5, 127, 128, 254, 255):
        img = np.full((12, 18, 3), value, np.uint8)
        assert np.array_equal(area_resize(img, (6, 4)), _opencv(img, (6, 4)))
    ramp = (np.add.outer(np.arange(360), np.arange(630)) % 256).astype(np.uint8)
    assert np.array_equal(area_resize(ramp, (210, 120)), _opencv(ramp, (210, 120)))


@pytest.mark.parametrize("offset", [(0, 0), (1, 2), (264, 339), (5, 7)])
def test_crops_and_views(offset: tuple[int, int]) -> None:
    """A crop of a frame (rows with the frame's stride), as the scene channel's working box cuts it."""
    rng = np.random.default_rng(7)
    frame = rng.integers(0, 256, (1080, 1920, 3), dtype=np.uint8)
    y, x = offset
    crop = frame[y:y + 723, x:x + 1242]
    assert not crop.flags.c_contiguous
    assert np.array_equal(area_resize(crop, (414, 241)), _opencv(crop, (414, 241)))
    grey = frame[..., 1][y:y + 300, x:x + 600]  # pixels 3 bytes apart: OpenCV's path
    assert np.array_equal(area_resize(grey, (200, 100)), _opencv(np.ascontiguousarray(grey), (200, 100)))
    flipped = frame[::-1, ::-1][:300, :600]  # negative strides: OpenCV's path
    assert np.array_equal(area_resize(flipped, (200, 100)), _opencv(np.ascontiguousarray(flipped), (200, 100)))


@pytest.mark.parametrize("shape,size", [((1080, 1920, 4), (640, 360)), ((1080, 1920), (960, 540)),
                                        ((720, 1280, 3), (640, 360)), ((1000, 1900), (640, 337))])
def test_other_inputs_are_opencvs(shape: tuple[int, ...], size: tuple[int, int]) -> None:
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    assert np.array_equal(area_resize(img, size), _opencv(img, size))
    f = img.astype(np.float32)
    assert np.array_equal(area_resize(f, size), _opencv(f, size))


def test_callers_give_opencvs_values() -> None:
    """The gate's reduced grey frame and the scene channel's working image (whole and cropped) as before."""
    rng = np.random.default_rng(11)
    frame = cv2.GaussianBlur(rng.integers(0, 256, (1080, 1920, 3), dtype=np.uint8), (0, 0), 2.0)
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    assert np.array_equal(compact_previous(frame), _opencv(grey, (640, 360)))
    want = cv2.GaussianBlur(_opencv(frame, (640, 360)).astype(np.float32), (0, 0), 0.7)
    assert np.array_equal(to_working(frame, (640, 360)), want)
    box = (slice(91, 326), slice(116, 524))
    crop, (y0, x0) = working_crop(frame, (640, 360), box)
    assert np.array_equal(crop[91 - y0:326 - y0, 116 - x0:524 - x0], want[box])
