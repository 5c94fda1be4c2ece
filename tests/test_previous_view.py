"""The print's previous photo kept as the next plane shows it (``layerwatch.pipeline.previous_view``)."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.part_registration import crop_box
from layerwatch.analysis.scoring import grey_u8
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.warp import TopViewWarper
from layerwatch.pipeline.checks import print_reach_mm
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.previous_view import PreviousView, typing_area
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import PrintSimulator, default_camera


@pytest.fixture(scope="module")
def scene():
    tp = read_toolpath(PART_GCODE)
    tv = resolve_config(PART_CONFIG).config.topview.topview()
    camera = default_camera(tv, image_size=(1920, 1080))
    photo = PrintSimulator(tp, camera, tv, [], seed=3).frame(20).photo
    return tp, tv, TopViewWarper(camera, tv), photo


def _shifted(box, shift):
    dx, dy = shift
    return slice(box[0].start + dy, box[0].stop + dy), slice(box[1].start + dx, box[1].stop + dx)


@pytest.mark.parametrize("shift", [(0, 0), (3, -2)])
def test_on_the_kept_plane_a_box_is_the_warp_of_the_photo_itself_bit_for_bit(scene, shift):
    tp, tv, warper, photo = scene
    z = float(tp.layers[21].z)
    area = typing_area(print_reach_mm(tp), tv)
    kept = PreviousView.capture(warper, photo, 20, z, area, shift)
    assert kept is not None
    for box in (area, (slice(area[0].start + 40, area[0].start + 200), slice(area[1].start + 7, area[1].stop - 31))):
        top, valid = kept.top(warper, z, box)
        want, want_valid = warper.warp(photo, z, box=_shifted(box, shift))
        assert np.array_equal(top, grey_u8(want)) and np.array_equal(valid, want_valid)
    # a twentieth of the 1080p photo (6 MB): the print's surroundings at the top view's scale
    assert kept.nbytes < 0.06 * photo.nbytes


def test_another_plane_is_the_kept_view_moved_through_the_planes_homography(scene):
    """A photo of a later layer than expected: the kept view on that plane agrees with the photo's own warp up to
    the second bilinear sampling, and is unseen where the kept box did not reach."""
    tp, tv, warper, photo = scene
    area = typing_area(print_reach_mm(tp), tv)
    kept = PreviousView.capture(warper, photo, 20, float(tp.layers[21].z), area, (0, 0))
    z = float(tp.layers[26].z)  # 1 mm higher: several pixels of parallax
    top, valid = kept.top(warper, z, area)
    want, want_valid = warper.warp(photo, z, box=area)
    want = grey_u8(want)
    assert not np.array_equal(top, want)  # (not the same pixels: moved, not warped again)
    assert valid.mean() > 0.9 and not (valid & ~want_valid).any()
    diff = np.abs(top.astype(int) - want.astype(int))[valid]
    assert np.median(diff) <= 2 and np.percentile(diff, 99) < 40
    shifted, _ = kept.top(warper, float(tp.layers[21].z), _shifted(area, (0, 9)))  # partly beyond the kept box
    assert shifted is not None


def test_a_box_that_the_shift_moves_out_of_the_view_gives_none(scene):
    tp, tv, warper, photo = scene
    area = typing_area(print_reach_mm(tp), tv)
    kept = PreviousView.capture(warper, photo, 20, float(tp.layers[21].z), area, (-5, 0))
    assert kept.top(warper, float(tp.layers[21].z), (slice(10, 50), slice(0, 40))) is None


def test_the_typing_area_covers_every_layers_registration_crop(scene):
    tp, tv, warper, _ = scene
    pipe = LayerPipeline(tp, warper.camera, resolve_config(PART_CONFIG).config)
    area = typing_area(print_reach_mm(tp), tv)
    for i in (0, tp.n_layers // 2, tp.n_layers - 1):
        rows, cols = crop_box(pipe.footprint(i)[0], tv)
        assert area[0].start <= rows.start and rows.stop <= area[0].stop
        assert area[1].start <= cols.start and cols.stop <= area[1].stop
    assert typing_area(None, tv) == (slice(0, tv.shape[0]), slice(0, tv.shape[1]))
