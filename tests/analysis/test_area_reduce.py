"""analysis/area_reduce: OpenCV's INTER_AREA values, bit for bit, on every input the farm reduces by 3 or 1.5."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.analysis.area_reduce import _pair_weights, _reduce3, area_resize
from layerwatch.analysis.extrusion import box_texture, highpass
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


@pytest.mark.parametrize("shape,size", [((1080, 1920), (1280, 720)), ((1080, 1920, 3), (1280, 720)),
                                        ((612, 852, 3), (568, 408)), ((9, 15, 3), (10, 6)), ((3, 3), (2, 2)),
                                        ((21, 33, 3), (22, 14)), ((6, 9), (6, 4))])
def test_by_one_and_a_half(shape: tuple[int, ...], size: tuple[int, int]) -> None:
    """The nothing-extruded check's working image (1920 -> 1280 px): random, extreme and smooth values."""
    rng = np.random.default_rng(sum(shape))
    assert _pair_weights(shape[1], size[0]) is not None and _pair_weights(shape[0], size[1]) is not None
    for img in (rng.integers(0, 256, shape, dtype=np.uint8), np.full(shape, 255, np.uint8),
                np.full(shape, 1, np.uint8), rng.integers(250, 256, shape, dtype=np.uint8),
                (np.indices(shape).sum(0) % 256).astype(np.uint8)):
        assert np.array_equal(area_resize(img, size), _opencv(img, size))


@pytest.mark.parametrize("offset", [(0, 0), (1, 3), (222, 534), (7, 5)])
def test_by_one_and_a_half_on_crops(offset: tuple[int, int]) -> None:
    rng = np.random.default_rng(5)
    frame = cv2.GaussianBlur(rng.integers(0, 256, (1080, 1920, 3), dtype=np.uint8), (0, 0), 1.0)
    y, x = offset
    for crop, size in ((frame[y:y + 612, x:x + 852], (568, 408)), (frame[y:y + 99, x:x + 201], (134, 66))):
        assert np.array_equal(area_resize(crop, size), _opencv(crop, size))


def test_other_tables_are_opencvs() -> None:
    """Scales whose tables are not two taps of 2/3 and 1/3 (1.25, 1.9, 2.5, 4) go to OpenCV, with its values."""
    rng = np.random.default_rng(9)
    for shape, size in (((100, 125, 3), (100, 80)), ((190, 190), (100, 100)), ((50, 125, 3), (50, 20)),
                        ((64, 64), (16, 16))):
        assert _pair_weights(shape[1], size[0]) is None or _pair_weights(shape[0], size[1]) is None
        img = rng.integers(0, 256, shape, dtype=np.uint8)
        assert np.array_equal(area_resize(img, size), _opencv(img, size))


def test_box_texture_is_the_whole_images() -> None:
    """The nothing-extruded check's texture of a box (1280 x 720 working image) as on the whole image."""
    rng = np.random.default_rng(13)
    frame = cv2.GaussianBlur(rng.integers(0, 256, (1080, 1920, 3), dtype=np.uint8), (0, 0), 1.5)
    size, box = (1280, 720), (slice(160, 544), slice(368, 912))
    whole = highpass(cv2.GaussianBlur(_opencv(frame, size).astype(np.float32), (0, 0), 0.7))
    assert np.array_equal(box_texture(frame, size, box), whole[box])
