"""The top-view warper: sub-pixel alignment for planes Z = 0..100 mm, distortion, resolution, masks."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from geometry_scenes import posed_camera

from layerwatch.errors import LayerwatchError, WarpError
from layerwatch.geometry.homography import top_from_image
from layerwatch.geometry.markers import detect_dots
from layerwatch.geometry.synthetic import render_bed_scene
from layerwatch.geometry.topview import TopView
from layerwatch.geometry.warp import TopViewWarper, occlusion_hint

DOTS = np.array([[-30.0, -30.0], [30.0, -30.0], [30.0, 30.0], [-30.0, 30.0]])


def _dot_centres(top: np.ndarray, expected_px: np.ndarray) -> np.ndarray:
    blobs = detect_dots(top, max_candidates=10)
    c = np.array([b.center for b in blobs])
    return np.array([c[np.argmin(np.linalg.norm(c - e, axis=1))] for e in expected_px])


@pytest.mark.parametrize("z", [0.0, 33.3, 66.7, 100.0])
def test_dots_on_plane_z_land_within_a_pixel(topview, z):
    from geometry_scenes import posed_camera

    camera = posed_camera(eye=(20.0, -230.0, 320.0))  # far enough to see the raised planes whole
    photo = render_bed_scene(camera, DOTS, 6.0, plane_z_mm=z, noise=2.0, blur=0.8, supersample=2,
                             bed_extent_mm=140, seed=int(z))
    top, valid = TopViewWarper(camera, topview).warp(photo, z)
    assert valid.all()
    assert top.shape == (600, 600, 3) and valid.dtype == bool
    expected = topview.to_px(DOTS)
    err = np.linalg.norm(_dot_centres(top, expected) - expected, axis=1)
    assert err.max() <= 1.0, err


def _float_map(warper, z, size):
    map1, map2, _ = warper.maps(z, size)
    return cv2.convertMaps(map1, map2, cv2.CV_32FC2)[0]


@pytest.mark.parametrize("z", [0.0, 50.0, 100.0])
def test_remap_table_matches_projectpoints_with_distortion(topview, z):
    """Every top-view pixel samples the photo where cv2.projectPoints (with distortion) puts its bed point."""
    from geometry_scenes import posed_camera

    camera = posed_camera(eye=(20.0, -230.0, 320.0), dist=(-0.2, 0.05, 0.001, 0.0, 0.0))
    src = _float_map(TopViewWarper(camera, topview), z, camera.image_size)
    v, u = np.mgrid[0:600:37, 0:600:37]
    u = np.r_[u.ravel(), 0, 599, 599, 0]
    v = np.r_[v.ravel(), 0, 0, 599, 599]  # include the four corners
    xy = topview.to_mm(np.c_[u, v].astype(float))
    ref = cv2.projectPoints(np.c_[xy, np.full(len(xy), z)], camera.rvec, camera.tvec, camera.K,
                            camera.dist)[0].reshape(-1, 2)
    got = src[v, u]
    inside = (ref[:, 0] > 0) & (ref[:, 0] < 959) & (ref[:, 1] > 0) & (ref[:, 1] < 539)
    assert inside.sum() > 0.95 * len(ref)
    # fixed-point tables quantise to 1/32 px; bilinear lookups add a little more
    assert np.abs(got[inside] - ref[inside]).max() < 0.15


def test_strong_distortion_matches_naive_undistort_then_warp(topview):
    from geometry_scenes import posed_camera

    cam = posed_camera(dist=(-0.3, 0.09, 0.001, -0.001, 0.0))
    photo = render_bed_scene(cam, topview.corners_mm, 6.0, texture="pei", noise=0, blur=1.0, supersample=2)
    top, valid = TopViewWarper(cam, topview).warp(photo, 0.0)
    und = cv2.undistort(photo, cam.K, cam.dist)
    naive = cv2.warpPerspective(und, top_from_image(cam, topview, 0.0), (600, 600), flags=cv2.INTER_LINEAR)
    inner = valid.copy()
    inner[:20], inner[-20:], inner[:, :20], inner[:, -20:] = False, False, False, False
    diff = np.abs(top.astype(int) - naive.astype(int))[inner]
    assert diff.mean() < 2.0
    # ignoring the distortion would be visibly wrong: the grid lines move
    nodist = replace(cam, dist=np.zeros(5))
    wrong, _ = TopViewWarper(nodist, topview).warp(photo, 0.0)
    assert np.abs(wrong.astype(int) - naive.astype(int))[inner].mean() > 3 * diff.mean()


def test_photo_of_another_resolution_uses_scaled_K(camera, topview):
    small = camera.scaled_to((480, 270))
    photo = render_bed_scene(small, DOTS, 6.0, supersample=3, bed_extent_mm=140, seed=3)
    top, _ = TopViewWarper(camera, topview).warp(photo, 0.0)  # model from 960x540
    expected = topview.to_px(DOTS)
    assert np.linalg.norm(_dot_centres(top, expected) - expected, axis=1).max() <= 1.0


def test_wrong_aspect_and_bad_arrays_raise_clear_errors(camera, topview):
    w = TopViewWarper(camera, topview)
    with pytest.raises(WarpError, match="aspect ratio"):
        w.warp(np.zeros((480, 480, 3), np.uint8), 0.0)
    with pytest.raises(WarpError, match="8-bit"):
        w.warp(np.zeros((540, 960, 3), np.float64), 0.0)
    with pytest.raises(WarpError, match="NumPy"):
        w.warp("photo.jpg", 0.0)
    with pytest.raises(WarpError, match="finite"):
        w.warp(np.zeros((540, 960), np.uint8), float("nan"))
    with pytest.raises(LayerwatchError, match="pose"):
        TopViewWarper(replace(camera, rvec=None, tvec=None), topview)


def test_validity_mask_marks_what_the_camera_did_not_see(topview):
    from geometry_scenes import posed_camera

    from layerwatch.geometry.topview import TopView

    cam = posed_camera(eye=(0.0, -120.0, 60.0), target=(0.0, 60.0, 0.0))  # low camera, near edge cut off
    wide = TopView(4.0, 200.0, 200.0, (0.0, 0.0))
    photo = np.full((540, 960, 3), 200, np.uint8)
    top, valid = TopViewWarper(cam, wide).warp(photo, 0.0)
    assert 0.05 < valid.mean() < 0.95
    assert np.all(top[~valid] == 0) and np.all(top[valid][:, 0] > 0)
    # the mask is exactly where the projected bed point falls inside the photo
    v, u = np.mgrid[0:800:23, 0:800:23]
    xy = wide.to_mm(np.c_[u.ravel(), v.ravel()].astype(float))
    uv = cv2.projectPoints(np.c_[xy, np.zeros(len(xy))], cam.rvec, cam.tvec, cam.K, cam.dist)[0].reshape(-1, 2)
    depth = (np.c_[xy, np.zeros(len(xy))] @ cam.R.T + cam.tvec)[:, 2]
    inside = (depth > 0) & (uv[:, 0] >= 1) & (uv[:, 0] <= 958) & (uv[:, 1] >= 1) & (uv[:, 1] <= 538)
    outside = (depth <= 0) | (uv[:, 0] < -1) | (uv[:, 0] > 960) | (uv[:, 1] < -1) | (uv[:, 1] > 540)
    got = valid[v.ravel(), u.ravel()]
    assert got[inside].all() and not got[outside].any()


def test_tables_are_cached_per_height(camera, topview):
    w = TopViewWarper(camera, topview, cache_size=2)
    a = w.maps(1.0)
    assert w.maps(1.0) is a
    w.maps(2.0), w.maps(3.0)
    assert w.maps(1.0) is not a


def test_occlusion_hint_flags_the_far_side_of_a_tall_part(camera, topview):
    occ = occlusion_hint(camera, topview, 0.0, (-10, -10, 10, 10), 40.0)
    near, far = topview.to_px([[0, -20]]), topview.to_px([[0, 20]])
    assert occ[int(far[0, 1]), int(far[0, 0])]          # behind the part, seen from the front
    assert not occ[int(near[0, 1]), int(near[0, 0])]    # in front of it
    assert not occlusion_hint(camera, topview, 40.0, (-10, -10, 10, 10), 40.0)[299, 299]  # its own top
    assert not occlusion_hint(camera, topview, 0.0, (-10, -10, 10, 10), 0.0).any()


def test_a_box_of_the_warp_is_the_whole_warp_cropped_pixel_for_pixel():
    from layerwatch.simulate import default_camera

    cam = default_camera(TopView(4.0, 100, 80, (0, 0)), image_size=(640, 360))
    tv = TopView(2.0, 400, 300, (0, 0))  # more than the camera sees: the unseen part is blanked
    rng = np.random.default_rng(3)
    photo = rng.integers(0, 256, (360, 640, 3), dtype=np.uint8)
    box = (slice(37, 511), slice(5, 390))
    whole = TopViewWarper(cam, tv).warp(photo, 2.4)
    part = TopViewWarper(cam, tv).warp(photo, 2.4, box)  # a fresh warper: the table is built for the box
    assert not whole[1][box].all() and whole[1][box].any()
    assert np.array_equal(part[0], whole[0][box]) and np.array_equal(part[1], whole[1][box])
    cached = TopViewWarper(cam, tv)
    cached.warp(photo, 2.4)
    assert np.array_equal(cached.warp(photo, 2.4, box)[0], whole[0][box])  # from the cached table
    with pytest.raises(WarpError, match="without a step"):
        TopViewWarper(cam, tv).warp(photo, 2.4, (slice(0, 10, 2), slice(0, 10)))


def test_a_kept_box_warps_the_next_photo_as_a_fresh_table_does():
    """keep_box: the box of a plane's tables survives clear() and gives the next photo's box warp pixel for
    pixel; nothing is kept for a plane that is not cached, and another box or plane builds its own table."""
    from layerwatch.simulate import default_camera

    cam = default_camera(TopView(4.0, 100, 80, (0, 0)), image_size=(640, 360))
    tv = TopView(2.0, 400, 300, (0, 0))
    rng = np.random.default_rng(5)
    first, second = (rng.integers(0, 256, (360, 640, 3), dtype=np.uint8) for _ in range(2))
    box = (slice(37, 511), slice(5, 390))
    warper = TopViewWarper(cam, tv, cache_size=1)
    assert not warper.keep_box(2.4, box, (640, 360))  # not warped on that plane yet
    warper.warp(first, 2.4)
    assert warper.keep_box(2.4, box, (640, 360))
    warper.clear(lookups=True)
    warper.warp(first, 2.6)  # the next layer's analysis
    fresh = TopViewWarper(cam, tv)
    for b, z in ((box, 2.4), ((slice(40, 500), slice(5, 390)), 2.4), (box, 2.6)):
        got, want = warper.warp(second, z, b), fresh.warp(second, z, b)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert warper._kept is not None and warper._kept[2].shape[:2] == (238, 194)  # the half-resolution crop only
    # every box on every edge of the top view, from a kept crop: the fresh table's pixels
    H, W = tv.shape
    for b in ((slice(0, 7), slice(0, 9)), (slice(H - 5, H), slice(W - 6, W)), (slice(1, H - 1), slice(2, 3)),
              (slice(0, H), slice(0, W)), (slice(100, 101), slice(333, 334))):
        warper.warp(first, 2.8)
        assert warper.keep_box(2.8, b, (640, 360))
        warper.clear()
        got, want = warper.warp(second, 2.8, b), fresh.warp(second, 2.8, b)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


@pytest.mark.parametrize("dist", [(-0.3, 0.09, 0.001, -0.001, 0.0), (-0.5, 0.0, 0.0, 0.0, 0.0)])
def test_a_lookup_rebuilt_after_clear_is_the_fresh_one_with_its_kept_fold_back_mask(topview, dist):
    """clear(lookups=True) keeps only the fold-back mask (bits); the lookup rebuilt from it is a fresh warper's,
    bit for bit, at the camera's size and another (a lens that folds back inside the lookup, and one that does not)."""
    cam = posed_camera(dist=dist)
    warper = TopViewWarper(cam, topview)
    for size in (cam.image_size, (cam.image_size[0] // 2, cam.image_size[1] // 2)):
        first = warper._lookup(size)[2].copy()
        warper.clear(lookups=True)
        assert size in warper._folds and size not in warper._lookups
        again, fresh = warper._lookup(size)[2], TopViewWarper(cam, topview)._lookup(size)[2]
        assert np.array_equal(again, fresh) and np.array_equal(first, fresh)
        far = (fresh[..., 0] == -1.0e4).sum()
        assert far < fresh.shape[0] * fresh.shape[1] and (far > 0) == (dist[0] == -0.5)  # the strong lens folds


@pytest.mark.parametrize("dist", [(-0.08, 0.02, 0.0, 0.0, 0.0), (-0.5, 0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0, 0.0)])
def test_tables_from_the_lookup_crop_kept_past_clear_are_the_whole_lookups(topview, dist):
    """A farm printer's warper drops its lookup after every layer (clear(lookups=True)) but keeps the crop that the
    planes' warps read: every table it makes from that crop (layers rising, a plane above the crop's reach, a
    restart at the bed, the lag check's lower plane, a box) is a fresh warper's, bit for bit, and the lookup is
    built whole only when a plane reads beyond the crop."""
    cam = posed_camera(dist=dist)
    size = tuple(cam.image_size)
    warper = TopViewWarper(cam, topview)
    built = []
    real = warper._lookup
    warper._lookup = lambda s: (built.append(s) if s not in warper._lookups else None, real(s))[1]  # type: ignore[method-assign]
    heights = [*np.arange(0.2, 12.0, 0.3), 30.0, 30.3, 0.2, 0.5]
    for z in heights:
        for zz in (z, max(z - 0.3, 0.0)):  # the layer's plane, then the lag check's plane of the layer below
            got, want = warper.maps(zz, size), TopViewWarper(cam, topview).maps(zz, size)
            for a, b in zip(got, want, strict=True):
                assert np.array_equal(a, b), (z, zz)
        box = (slice(200, 320), slice(150, 420))
        photo = np.random.default_rng(int(z * 10)).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
        warper.clear()
        got, want = warper.warp(photo, z, box), TopViewWarper(cam, topview).warp(photo, z, box)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        warper.clear(lookups=True)
        assert size not in warper._lookups and size in warper._crops
    # whole at the first plane and again every ~5 mm of rise, at 30 mm and at the restart
    assert 2 <= len(built) <= 6, built
    rows, cols, crop, _, _ = warper._crops[size]
    whole = TopViewWarper(cam, topview)._lookup(size)[2]
    assert crop.nbytes < 0.6 * whole.nbytes  # the crop is what a printer holds, not the whole lookup
