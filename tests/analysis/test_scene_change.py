"""The scene channel's pure functions: projection of the predicted change, photometric fit, change blocks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.analysis.result import LayerResult, Region, SceneStats
from layerwatch.analysis.scene_change import (
    SATURATED,
    _morph_near,
    change_blocks,
    change_regions,
    image_rays,
    photometric_fit,
    plane_maps,
    predicted_change,
    rays_over,
    to_working,
    top_coords,
    working_crop,
    working_size,
)
from layerwatch.analysis.settings import SceneSettings
from layerwatch.errors import AnalysisError
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.scene import _saturated
from layerwatch.simulate.scene import default_camera

TV = TopView(4.0, 90.0, 90.0, (110.0, 100.0))


def _texture(h=180, w=320, seed=0) -> np.ndarray:
    """A bed-like texture (grey levels ~ 60-110), float32 (h, w, 3)."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.normal(85, 25, (h, w)).astype(np.float32), (0, 0), 1.2)
    return np.repeat(base[..., None], 3, axis=2) * np.array([1.0, 0.95, 0.9], np.float32)


def _noisy(img, seed=1, sigma=1.5):
    return (img + np.random.default_rng(seed).normal(0, sigma, img.shape)).astype(np.float32)


def test_plane_maps_put_each_pixel_where_the_camera_projects_its_bed_point():
    cam = default_camera(TV, image_size=(640, 360))
    maps = plane_maps(image_rays(cam, (640, 360)), cam.center_mm, TV)
    for z in (0.0, 7.5):
        mx, my = top_coords(maps, z)
        for u, v in ((100, 200), (320, 180), (500, 300)):
            xy = TV.to_mm(np.array([mx[v, u], my[v, u]], float))
            uv = cv2.projectPoints(np.array([[*xy, z]]), cam.rvec, cam.tvec, cam.K, cam.dist)[0].reshape(2)
            assert np.allclose(uv, (u, v), atol=0.05)


def test_rays_over_keeps_exactly_the_pixels_whose_ray_crosses_the_rectangle_between_the_heights():
    """Against the ray sampled at 401 heights: no pixel missed, none kept that the samples never put inside."""
    cam = default_camera(TV, image_size=(320, 180))
    maps = plane_maps(image_rays(cam, (320, 180)), cam.center_mm, TV)
    rect = (250.0, 260.0, 330.0, 340.0)
    keep = rays_over(maps, rect, -1.0, 20.0)
    inside = np.zeros(keep.shape, bool)
    for z in np.linspace(-1.0, 20.0, 401):
        mx, my = top_coords(maps, z)
        inside |= (mx >= rect[0]) & (mx <= rect[2]) & (my >= rect[1]) & (my <= rect[3])
    assert inside.any() and not (inside & ~keep).any()  # every sampled crossing is kept
    assert (keep & ~inside).sum() <= 0.02 * keep.sum()  # what the samples missed: grazing rays only
    assert not rays_over(maps, (5000.0, 5000.0, 5100.0, 5100.0), 0.0, 10.0).any()  # where no ray goes


def test_predicted_change_is_the_footprint_where_the_camera_sees_it_and_grows_with_the_margin():
    cam = default_camera(TV, image_size=(640, 360))
    maps = plane_maps(image_rays(cam, (640, 360)), cam.center_mm, TV)
    fp = np.zeros(TV.shape, bool)
    (u0, v1), (u1, v0) = np.round(TV.to_px(np.array([[100.0, 90.0], [120.0, 110.0]]))).astype(int)
    fp[v0:v1, u0:u1] = True
    m0 = predicted_change(fp, (4.8, 5.0), maps, TV, 0.0)
    m2 = predicted_change(fp, (4.8, 5.0), maps, TV, 2.0)
    inner = predicted_change(fp, (5.0,), maps, TV, -2.0)
    centre = cv2.projectPoints(np.array([[110.0, 100.0, 5.0]]), cam.rvec, cam.tvec, cam.K, cam.dist)[0].reshape(2)
    assert m0[int(round(centre[1])), int(round(centre[0]))]
    assert m2.sum() > m0.sum() > inner.sum() > 0
    assert not (inner & ~m0).any() and not (m0 & ~m2).any()
    far = cv2.projectPoints(np.array([[75.0, 70.0, 0.0]]), cam.rvec, cam.tvec, cam.K, cam.dist)[0].reshape(2)
    assert not m2[int(far[1]), int(far[0])]


def test_predicted_change_takes_the_planes_coordinates_it_is_given_and_keeps_the_ones_it_computes():
    cam = default_camera(TV, image_size=(640, 360))
    maps = plane_maps(image_rays(cam, (640, 360)), cam.center_mm, TV)
    fp = np.zeros(TV.shape, bool)
    (u0, v1), (u1, v0) = np.round(TV.to_px(np.array([[100.0, 90.0], [120.0, 110.0]]))).astype(int)
    fp[v0:v1, u0:u1] = True
    planes: dict = {}
    m = predicted_change(fp, (4.8, 5.0), maps, TV, 1.0, planes)
    assert np.array_equal(m, predicted_change(fp, (4.8, 5.0), maps, TV, 1.0))
    assert set(planes) == {4.8, 5.0}
    assert all(np.array_equal(c, w) for c, w in zip(planes[5.0], top_coords(maps, 5.0), strict=True))
    assert np.array_equal(predicted_change(fp, (5.0,), maps, TV, 0.0, planes), predicted_change(fp, (5.0,), maps, TV, 0.0))
    planes[5.0] = top_coords(maps, 0.0)  # what it is given is what it projects with
    assert np.array_equal(predicted_change(fp, (5.0,), maps, TV, 0.0, planes), predicted_change(fp, (0.0,), maps, TV, 0.0))


def test_a_light_change_is_not_a_change_but_an_object_is():
    E = _texture()
    h, w = E.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    light = (1.25 + 0.25 * xx / w - 0.1 * yy / h)[..., None] * np.array([1.0, 1.05, 0.9], np.float32)  # exposure + WB
    photo = _noisy(np.minimum(E * light, 255))
    usable = np.ones((h, w), bool)
    st = SceneSettings()
    ratio, gain = photometric_fit(photo, E, usable)
    assert np.all(gain > 1.1)
    assert not change_blocks(photo, E, usable, ratio, st).changed.any()
    bad = photo.copy()
    cv2.circle(bad, (200, 90), 12, (20.0, 20.0, 25.0), -1)  # a dark nut
    for k in range(4):  # strands
        cv2.line(bad, (40, 40 + 6 * k), (120, 60 + 9 * k), (230.0, 200.0, 120.0), 2)
    ratio, _ = photometric_fit(bad, E, usable)
    ch = change_blocks(bad, E, usable, ratio, st)
    b = st.block_px
    assert ch.changed[90 // b, 200 // b] and ch.changed[50 // b, 80 // b]
    assert ch.changed.sum() < 0.1 * ch.scored.sum()


def test_a_moving_shade_is_explained_by_a_local_gain():
    E = _texture(seed=3)
    shade = np.ones(E.shape[:2], np.float32)
    shade[40:120, 60:200] = 0.8  # a soft shadow sweeping over the bed: brightness, not texture
    photo = _noisy(E * cv2.GaussianBlur(shade, (0, 0), 4.0)[..., None])
    usable = np.ones(E.shape[:2], bool)
    ratio = np.ones_like(E)  # as if the smooth fit had missed it entirely
    assert not change_blocks(photo, E, usable, ratio, SceneSettings()).changed.any()


def _fit_on_the_whole_image(photo, expected, usable, cell_px=32, smooth_cells=5):
    """photometric_fit as it was before it took the log ratio on the usable box only (the reference)."""
    from scipy import ndimage

    from layerwatch.analysis.scene_change import OUTLIER_LOG, channel_max
    h, w = usable.shape
    ok = np.ascontiguousarray(usable[::2, ::2]).astype(np.float32)
    lr = cv2.subtract(np.log1p(photo[::2, ::2]), np.log1p(expected[::2, ::2]))
    c = max(1, cell_px // 2)
    size = (-(-ok.shape[1] // c), -(-ok.shape[0] // c))
    glob = np.array([np.median(lr[..., k][ok > 0]) for k in range(3)])
    keep = ok
    for _ in range(2):
        frac = cv2.resize(keep, size, interpolation=cv2.INTER_AREA)
        mean = cv2.resize(lr * keep[..., None], size, interpolation=cv2.INTER_AREA) / np.maximum(frac, 1e-6)[..., None]
        mean = np.where((frac >= 0.25)[..., None], mean, glob).astype(np.float32)
        near = cv2.resize(mean, ok.shape[::-1], interpolation=cv2.INTER_NEAREST)
        keep = ok * (channel_max(np.abs(lr - near)) < OUTLIER_LOG).astype(np.float32)
    mean = ndimage.median_filter(mean, size=(smooth_cells, smooth_cells, 1), mode="nearest")
    field = cv2.resize(mean, (size[0] * cell_px, size[1] * cell_px), interpolation=cv2.INTER_LINEAR)[:h, :w]
    return np.exp(np.ascontiguousarray(field, np.float32)), np.exp(glob).astype(np.float64)


@pytest.mark.parametrize("box", [(slice(91, 326), slice(116, 524)), (slice(0, 360), slice(0, 640)),
                                 (slice(40, 41), slice(7, 600)), (slice(201, 360), slice(333, 640))])
def test_photometric_fit_on_the_usable_box_is_the_whole_image_fit_bit_for_bit(box):
    E = _texture(360, 640, seed=3)
    rng = np.random.default_rng(4)
    photo = _noisy(E * np.float32(1.2), seed=5)
    photo[100:140, 200:260] = 240.0  # an object: outliers of the fit
    usable = np.zeros(E.shape[:2], bool)
    usable[box] = rng.random(usable[box].shape) < 0.8
    ratio, gain = photometric_fit(photo, E, usable)
    want_ratio, want_gain = _fit_on_the_whole_image(photo, E, usable)
    assert np.array_equal(ratio, want_ratio) and np.array_equal(gain, want_gain)


def test_unusable_pixels_are_not_scored_and_a_black_frame_has_no_gain():
    E = _texture()
    usable = np.zeros(E.shape[:2], bool)
    usable[:, :100] = True
    ch = change_blocks(_noisy(E), E, usable, np.ones_like(E), SceneSettings())
    assert ch.scored[:, : 96 // 8].all() and not ch.scored[:, 104 // 8 :].any()
    _, gain = photometric_fit(np.zeros_like(E), E, np.ones(E.shape[:2], bool))
    assert np.all(gain < 0.1)


def test_to_working_reduces_and_refuses_odd_frames():
    assert working_size((1920, 1080), 640) == (640, 360)
    assert working_size((320, 180), 640) == (320, 180)
    img = to_working(np.full((1080, 1920, 3), 100, np.uint8), (640, 360))
    assert img.shape == (360, 640, 3) and img.dtype == np.float32 and np.allclose(img, 100)
    with pytest.raises(AnalysisError):
        to_working(np.zeros((1000, 1000, 3), np.uint8), (640, 360))
    with pytest.raises(AnalysisError):
        to_working(np.zeros((360, 640, 3), np.float32), (640, 360))


@pytest.mark.parametrize(("photo_size", "size"), [((1920, 1080), (640, 360)), ((1280, 720), (640, 360)),
                                                  ((1920, 1080), (1280, 720)), ((1920, 1080), (1000, 563))])
def test_working_crop_is_the_whole_working_image_on_the_box_bit_for_bit(photo_size, size):
    rng = np.random.default_rng(5)
    photo = rng.integers(0, 256, (photo_size[1], photo_size[0], 3), dtype=np.uint8)
    whole = to_working(photo, size)
    W, H = size
    cut = 0
    for _ in range(60):
        r0, c0 = int(rng.integers(0, H - 2)), int(rng.integers(0, W - 2))
        r1, c1 = int(rng.integers(r0 + 1, H + 1)), int(rng.integers(c0 + 1, W + 1))
        img, (y0, x0) = working_crop(photo, size, (slice(r0, r1), slice(c0, c1)))
        assert img.dtype == np.float32 and y0 <= r0 and x0 <= c0
        cut += img.shape[:2] != (H, W)
        assert np.array_equal(img[r0 - y0:r1 - y0, c0 - x0:c1 - x0], whole[r0:r1, c0:c1])
    assert cut > 30 if size != (1000, 563) else cut == 0  # most on their cut; 1920/1000 aligns only every 25 px
    with pytest.raises(AnalysisError):  # as to_working: another aspect ratio
        working_crop(np.zeros((1000, 1000, 3), np.uint8), (640, 360), (slice(10, 20), slice(10, 20)))


def test_change_regions_are_in_bed_mm_with_an_ordered_box():
    tv = TopView(5.0, 60.0, 60.0, (30.0, 30.0))
    changed = np.zeros(tv.shape, bool)
    (u0, v1), (u1, v0) = np.round(tv.to_px(np.array([[10.0, 40.0], [20.0, 50.0]]))).astype(int)
    changed[v0:v1, u0:u1] = True
    regions = change_regions(changed, np.where(changed, 0.5, 1.0).astype(np.float32), tv, 4.0)
    assert len(regions) == 1
    r = regions[0]
    x0, y0, x1, y1 = r.bbox_mm
    assert x0 < x1 and y0 < y1
    assert abs(r.area_mm2 - 100) < 10 and abs(r.centroid_mm[0] - 15) < 0.5 and abs(r.centroid_mm[1] - 45) < 0.5
    assert r.outside_fraction == 1.0 and r.mean_similarity == pytest.approx(0.5)
    assert change_regions(changed, np.ones(tv.shape, np.float32), tv, 200.0) == []


def test_layer_result_keeps_the_scene_fields_through_json():
    res = LayerResult(layer=3, z=0.9, outside_anomalous_mm2=12.5,
                      outside_regions=[Region(12.5, (1.0, 2.0, 3.0, 4.0), (2.0, 3.0), 4, 0.4, 0.3, 1.0)],
                      scene=SceneStats("bed photo", 8.0, 0.5, 900, 3, (1.0, 1.1, 0.9), 12.0))
    back = LayerResult.from_json(res.to_json())
    assert back.outside_anomalous_mm2 == 12.5
    assert back.outside_regions == res.outside_regions
    assert back.scene == res.scene
    assert LayerResult.from_json(LayerResult(layer=1, z=0.3).to_json()).scene is None


def test_compare_with_a_bed_photo_reports_what_changed_beside_the_footprint(tmp_path, capsys):
    from layerwatch.cli import main

    bed = np.clip(_texture(600, 600, seed=5), 0, 255).astype(np.uint8)
    top = bed.copy()
    top[200:400, 200:400] = 200  # the part (its footprint is the mask)
    cv2.circle(top, (480, 120), 25, (30, 30, 30), -1)  # a nut on the bed beside it
    mask = np.zeros((600, 600), np.uint8)
    mask[200:400, 200:400] = 255
    paths = {k: tmp_path / f"{k}.png" for k in ("top", "ref", "mask", "bed", "small")}
    for k, img in (("top", top), ("ref", top), ("mask", mask), ("bed", bed), ("small", bed[:300])):
        cv2.imwrite(str(paths[k]), img)
    args = ["compare", str(paths["top"]), str(paths["ref"]), "--mask", str(paths["mask"]), "-c", str(tmp_path / "j.toml")]
    (tmp_path / "j.toml").write_text("[topview]\npx_per_mm = 6.67\nwidth_mm = 90\nheight_mm = 90\ncenter_mm = [45, 45]\n")
    assert main([*args, "--bed-photo", str(paths["bed"]), "--json", str(tmp_path / "r.json")]) == 0
    res = LayerResult.from_json((tmp_path / "r.json").read_text())
    assert len(res.outside_regions) == 1 and res.outside_anomalous_mm2 > 20
    cx, cy = res.outside_regions[0].centroid_mm
    assert abs(cx - 480 / 6.67) < 3 and abs(cy - (90 - 120 / 6.67)) < 3
    capsys.readouterr()
    assert main([*args, "--bed-photo", str(paths["small"])]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert main(args) == 0
    assert "no --bed-photo" in capsys.readouterr().out


@pytest.mark.parametrize("dilate", [True, False])
def test_morphology_on_the_footprint_box_equals_the_whole_image_operation(dilate):
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (21, 21))
    rng = np.random.default_rng(4)
    for case in range(6):
        mask = np.zeros((200, 240), np.uint8)
        y, x = rng.integers(0, 170), rng.integers(0, 210)
        mask[y : y + 30, x : x + 30] = 1
        if case % 2:  # touching the image border: cv2's border rule must be the same on the box
            mask[:25, :18] = 1
        full = cv2.dilate(mask, se) if dilate else cv2.erode(mask, se)
        assert np.array_equal(_morph_near(mask, se, dilate=dilate), full)
    assert not _morph_near(np.zeros((50, 60), np.uint8), se, dilate=dilate).any()


def test_change_blocks_score_only_the_blocks_around_usable_pixels_and_equal_a_block_aligned_crop():
    E = _texture(240, 320)
    photo = _noisy(E)
    photo[100:124, 150:174] = 200.0  # an object
    usable = np.zeros(E.shape[:2], bool)
    usable[44:180, 60:250] = True
    ratio = np.ones_like(E)
    st = SceneSettings()
    full = change_blocks(photo, E, usable, ratio, st)
    crop = (slice(40, 184), slice(56, 256))  # block-aligned (8 px), holds every usable pixel
    part = change_blocks(photo[crop], E[crop], usable[crop], ratio[crop], st)
    inner = (slice(5, 23), slice(7, 32))
    assert np.array_equal(full.score[inner], part.score) and np.array_equal(full.changed[inner], part.changed)
    assert full.threshold == part.threshold and full.changed[13:15, 19:21].all()
    outside = np.ones(full.scored.shape, bool)
    outside[inner] = False
    assert not full.scored[outside].any() and not full.score[outside].any()
    none = change_blocks(photo, E, np.zeros_like(usable), ratio, st)
    assert not none.scored.any() and not none.changed.any() and none.changed_share == 0.0


def test_saturated_pixels_are_those_with_a_channel_at_or_above_the_limit():
    img = np.full((4, 5, 3), 100.0, np.float32)
    img[0, 0] = (SATURATED, 0, 0)
    img[0, 1] = (0, 0, np.nextafter(np.float32(SATURATED), np.float32(0)))  # just below: not saturated
    img[1, 2] = (0, 255.0, 0)
    want = np.zeros((4, 5), bool)
    want[0, 0] = want[1, 2] = True
    assert np.array_equal(_saturated(img), want)


def test_a_clipped_channel_only_bounds_its_value_and_an_object_on_a_clipped_floor_still_counts():
    """A bright orange floor whose red channel the camera clips: darker light must not look like change
    (the clipped red says only "this bright or brighter"), a blue object on it must (green and blue see it)."""
    h, w = 160, 320
    tex = _texture(h, w, seed=4)
    E = tex.copy()  # left: grey bed; right: orange floor, red clipped (its true value ~300)
    E[:, 160:] = np.stack([0.6 * tex[:, 160:, 0], 1.6 * tex[:, 160:, 0], np.full((h, 160), 255.0, np.float32)], -1)
    photo = _noisy(E * 0.9)  # the lamp dimmed by 10 %: the true red ~270 is still clipped
    photo[:, 160:, 2] = 255.0
    usable = np.ones((h, w), bool)
    fit = usable & (E < SATURATED).all(-1) & (photo < SATURATED).all(-1)  # the fit on unclipped pixels (the bed)
    ratio, gain = photometric_fit(photo, E, fit)
    assert np.allclose(gain, 0.9, atol=0.02)
    st = SceneSettings()
    plain = np.abs(photo - np.minimum(E * ratio, 255.0)).mean(-1)[:, 170:].mean()
    assert plain > st.min_change  # without the bound, the dimmed clipped floor would all read as change
    assert not change_blocks(photo, E, usable, ratio, st).changed.any()
    bad = photo.copy()
    cv2.rectangle(bad, (230, 60), (250, 90), (200.0, 120.0, 60.0), -1)  # a blue hex key on the floor
    ch = change_blocks(bad, E, usable, ratio, st)
    b = st.block_px
    assert ch.changed[75 // b, 240 // b]
    assert not ch.changed[:, : 230 // b].any() and not ch.changed[:, 250 // b + 1 :].any()  # only where it lies
