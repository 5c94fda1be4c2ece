"""The print's previous photo kept as the next plane shows it (``layerwatch.pipeline.previous_view``)."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.part_registration import crop_box
from layerwatch.analysis.scoring import grey_u8
from layerwatch.analysis.view_shift import moved_back
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


def _kept(tp, tv, warper, photo, shift):
    """Layer 20's photo as the step keeps it: its top view, its residual view shift undone."""
    z = float(tp.layers[20].z)
    bgr, valid = warper.warp(photo, z)
    top, valid, _ = moved_back(shift, grey_u8(bgr), valid, bgr)
    return PreviousView.keep(20, z, top, valid, typing_area(print_reach_mm(tp), tv), shift), top, valid


@pytest.mark.parametrize("shift", [(0, 0), (3, -2)])
def test_the_next_plane_is_the_photos_own_warp_up_to_a_second_bilinear_sampling(scene, shift):
    """What the typing of layer 21 (and of layer 25, after dropped photos) reads of layer 20's photo: the kept
    view moved through the planes' homography agrees with the photo warped onto that plane on the box that the
    view shift offsets, far better than with the box left in place (the shift is accounted for)."""
    tp, tv, warper, photo = scene
    kept, top20, _ = _kept(tp, tv, warper, photo, shift)
    area = kept.box
    inner = (slice(area[0].start + 30, area[0].stop - 30), slice(area[1].start + 30, area[1].stop - 30))
    for layer in (21, 25):
        z = float(tp.layers[layer].z)
        top, valid = kept.top(warper, z, inner)
        want, want_valid = warper.warp(photo, z, box=_shifted(inner, shift))
        want = grey_u8(want)
        assert valid.mean() > 0.95 and not (valid & ~want_valid).any()
        diff = np.abs(top.astype(int) - want.astype(int))[valid]
        assert np.median(diff) <= 1 and np.percentile(diff, 99) < 30, (np.median(diff), np.percentile(diff, 99))
        if shift != (0, 0):
            unshifted = grey_u8(warper.warp(photo, z, box=inner)[0])
            assert np.mean(np.abs(top.astype(int) - unshifted.astype(int))[valid]) > 1.5 * np.mean(diff)
        assert not np.array_equal(top, top20[inner])  # moved by the parallax, not the kept pixels as they are
    # on the kept plane: the kept pixels themselves
    top, valid = kept.top(warper, kept.z, inner)
    assert np.array_equal(top, top20[inner])
    # a twentieth of the 1080p photo (6 MB): the print's surroundings at the top view's scale
    assert kept.nbytes < 0.06 * photo.nbytes


def test_beyond_the_kept_view_is_unseen_and_an_empty_box_gives_none(scene):
    tp, tv, warper, photo = scene
    kept, _, _ = _kept(tp, tv, warper, photo, (0, 0))
    z = float(tp.layers[21].z)
    whole = (slice(0, tv.shape[0]), slice(0, tv.shape[1]))
    top, valid = kept.top(warper, z, whole)
    assert valid[kept.box].mean() > 0.9 and not valid[:kept.box[0].start - 2].any()
    assert (top[~valid] == 0).all()
    assert kept.top(warper, z, (slice(10, 10), slice(0, 40))) is None


def test_the_typing_area_covers_every_layers_registration_crop(scene):
    tp, tv, warper, _ = scene
    pipe = LayerPipeline(tp, warper.camera, resolve_config(PART_CONFIG).config)
    area = typing_area(print_reach_mm(tp), tv)
    for i in (0, tp.n_layers // 2, tp.n_layers - 1):
        rows, cols = crop_box(pipe.footprint(i)[0], tv)
        assert area[0].start <= rows.start and rows.stop <= area[0].stop
        assert area[1].start <= cols.start and cols.stop <= area[1].stop
    assert typing_area(None, tv) == (slice(0, tv.shape[0]), slice(0, tv.shape[1]))
