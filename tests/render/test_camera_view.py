"""The camera-view reference: walls facing the camera, parallax, occlusion."""

import numpy as np
import pytest

from layerwatch.geometry.topview import TopView
from layerwatch.render.camera_view import WallLook, view_from_camera

TV = TopView(10.0, 40.0, 40.0, (0.0, 0.0))  # 10 px/mm, 400 x 400 px, bed (-20..20) mm


def _box_scene(h_mm=5.0):
    """A 10 x 10 mm box of height ``h_mm`` at the centre; top bright (1.0), bed dark (0.1)."""
    height = np.zeros(TV.shape, np.float32)
    shaded = np.full(TV.shape, 0.1, np.float32)
    (u0, v1), (u1, v0) = np.round(TV.to_px(np.array([[-5.0, -5.0], [5.0, 5.0]]))).astype(int)
    height[v0 : v1 + 1, u0 : u1 + 1] = h_mm
    shaded[v0 : v1 + 1, u0 : u1 + 1] = 1.0
    return height, shaded, (u0, u1, v0, v1)


def test_wall_band_in_front_of_the_box_and_bed_behind_it():
    h = 5.0
    height, shaded, (u0, u1, v0, v1) = _box_scene(h)
    # camera in front of the printer (-Y), 45 deg: 100 mm back, 100 mm up (plus the box height)
    cam = np.array([0.0, -100.0, 100.0 + h])
    img, hit = view_from_camera(height, shaded, cam, TV, h, look=WallLook(wall_value=0.5, wall_line_contrast=0.0))
    u = (u0 + u1) // 2
    # top of the box: seen where it is
    assert img[(v0 + v1) // 2, u] == pytest.approx(1.0)
    assert hit[(v0 + v1) // 2, u] == pytest.approx(h)
    # in front of the box (towards the camera = larger v in the image), a band of about h mm shows the wall
    band = img[v1 + 1 : v1 + 1 + 60, u]
    walls = np.flatnonzero(np.isclose(band, 0.5))
    assert walls.size > 0 and walls[0] <= 1
    assert walls.size == pytest.approx(h * TV.px_per_mm * 1.0, abs=6)  # 45 deg: 1 mm of plane per mm of height
    assert np.allclose(img[v1 + 70 : v1 + 90, u], 0.1)  # then the bed
    # behind the box (away from the camera) the rays go down to the bed: no wall there
    assert np.allclose(img[v0 - 30 : v0 - 1, u], 0.1)


def test_lower_surfaces_shift_towards_the_camera():
    """A mark on the bed is seen through the plane z = h displaced towards the camera (parallax)."""
    h = 4.0
    height = np.zeros(TV.shape, np.float32)
    shaded = np.full(TV.shape, 0.1, np.float32)
    (um, vm) = np.round(TV.to_px(np.array([0.0, 0.0]))).astype(int)
    shaded[vm - 2 : vm + 3, um - 2 : um + 3] = 1.0
    cam = np.array([0.0, -100.0, 100.0])
    img, _ = view_from_camera(height, shaded, cam, TV, h)
    v, u = np.unravel_index(np.argmax(img), img.shape)
    # the ray through plane point P reaches the bed at P + (P - C) * h / (C_z - h); it meets the
    # mark (y = 0) for P_y + (P_y - C_y) * h / (C_z - h) = 0, i.e. P_y = C_y * h / C_z
    expect_y = cam[1] * h / cam[2]
    got = TV.to_mm(np.array([u, v], float))
    assert got[1] == pytest.approx(expect_y, abs=0.3)
    assert got[0] == pytest.approx(0.0, abs=0.3)


def test_camera_overhead_gives_the_top_view_of_top_surfaces():
    height, shaded, (u0, u1, v0, v1) = _box_scene(2.0)
    img, _ = view_from_camera(height, shaded, np.array([0.0, 0.0, 5000.0]), TV, 2.0)
    assert np.allclose(img[v0 + 2 : v1 - 1, u0 + 2 : u1 - 1], 1.0)
    assert np.allclose(img[5:20, 5:20], 0.1)


def test_camera_below_the_plane_is_refused():
    height, shaded, _ = _box_scene()
    with pytest.raises(ValueError, match="above the layer plane"):
        view_from_camera(height, shaded, np.array([0.0, -50.0, 3.0]), TV, 5.0)


def test_a_ray_stopped_by_the_depth_limit_shows_what_lies_under_it_there():
    """Past ``max_depth_mm`` the ray's current point is shown, not the plane point it started from."""
    height = np.zeros(TV.shape, np.float32)
    rows = np.arange(TV.shape[0], dtype=np.float32)[:, None]
    shaded = np.repeat(rows / TV.shape[0], TV.shape[1], axis=1)  # brightness = row / H
    cam = np.array([0.0, -100.0, 110.0])  # 45 deg onto the plane z = 10 at the centre
    v, u = TV.shape[0] // 2, TV.shape[1] // 2
    deep, _ = view_from_camera(height, shaded, cam, TV, 10.0, look=WallLook(max_depth_mm=30.0))
    # reaches the bed 10 mm further from the camera (+Y = 100 rows up)
    assert deep[v, u] == pytest.approx((v - 100) / TV.shape[0], abs=3 / TV.shape[0])
    short, _ = view_from_camera(height, shaded, cam, TV, 10.0, look=WallLook(max_depth_mm=2.0))
    # stopped at least 2 mm down: at least 20 rows away from the start, short of the bed
    assert (v - 100) / TV.shape[0] < short[v, u] <= (v - 19) / TV.shape[0]
