"""Markers and pose on synthetic photos with known ground truth; refusals of bad photos."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from geometry_scenes import posed_camera, rotation_error_deg

from layerwatch.errors import CalibrationError, LayerwatchError, MarkerError
from layerwatch.geometry.pose import camera_moved, locate_bed, solve_pose
from layerwatch.geometry.settings import MarkerSettings
from layerwatch.geometry.synthetic import project_points, render_bed_scene

SCENES = {
    "plain": dict(texture="plain", noise=3.0, blur=1.2),
    "textured": dict(texture="pei", noise=4.0, blur=1.0),
    "glare": dict(texture="pei", glare=0.6, noise=3.0, blur=0.8),
    "light bed": dict(bed_rgb=(120, 120, 125), texture="grid", noise=3.0, blur=1.0),
}


def _unposed(cam):
    return replace(cam, rvec=None, tvec=None)


@pytest.mark.parametrize("scene", list(SCENES))
def test_pose_error_within_half_degree_and_a_millimetre(camera, topview, scene):
    photo = render_bed_scene(camera, topview.corners_mm, 6.0, supersample=2, seed=7, **SCENES[scene])
    est = locate_bed(_unposed(camera), photo, MarkerSettings(), topview)
    assert rotation_error_deg(est, camera) <= 0.5
    assert np.abs(est.tvec - camera.tvec).max() <= 1.0
    assert np.linalg.norm(est.center_mm - camera.center_mm) <= 1.0
    assert est.errors["pose_px"] < 0.5 and est.markers_mm.shape == (4, 2)


def test_marker_order_follows_the_camera_side(topview):
    """A square looks alike from four sides; the configured camera azimuth picks the right one."""
    side = posed_camera(eye=(-200.0, 30.0, 180.0))  # camera on the left of the printer
    photo = render_bed_scene(side, topview.corners_mm, 6.0, supersample=2, seed=1)
    est = locate_bed(_unposed(side), photo, MarkerSettings(camera_azimuth_deg=180.0), topview)
    assert np.linalg.norm(est.center_mm - side.center_mm) <= 1.0
    # a non-square layout needs no cue at all
    layout = [(-40.0, -30.0), (45.0, -35.0), (35.0, 40.0), (-30.0, 25.0)]
    photo = render_bed_scene(side, layout, 6.0, supersample=2, seed=2)
    est = locate_bed(_unposed(side), photo, MarkerSettings(positions_mm=layout), topview)
    assert np.linalg.norm(est.center_mm - side.center_mm) <= 1.0


def test_aruco_markers(camera, topview):
    photo = render_bed_scene(camera, topview.corners_mm, 14.0, aruco_dictionary="DICT_4X4_50",
                             supersample=2, noise=2.0, blur=0.7, seed=3)
    est = locate_bed(_unposed(camera), photo, MarkerSettings(kind="aruco"), topview)
    assert rotation_error_deg(est, camera) <= 0.5
    assert np.linalg.norm(est.center_mm - camera.center_mm) <= 2.0
    with pytest.raises(MarkerError, match="not found"):
        locate_bed(camera, photo, MarkerSettings(kind="aruco", positions_mm=[(0, 0)] * 5), topview)


def test_solve_pose_exact_points_and_refusals(camera, topview):
    pts = project_points(camera, topview.corners_mm)
    est = solve_pose(camera, pts, topview.corners_mm)
    assert rotation_error_deg(est, camera) < 1e-4 and est.errors["pose_px"] < 1e-6
    with pytest.raises(MarkerError, match="reprojection error"):
        solve_pose(camera, pts + [[0, 0], [0, 0], [25, 0], [0, 0]], topview.corners_mm)
    with pytest.raises(MarkerError):  # mirrored order: camera would be under the bed
        solve_pose(camera, pts[[1, 0, 3, 2]], topview.corners_mm)
    with pytest.raises(MarkerError, match="same number"):
        solve_pose(camera, pts[:3], topview.corners_mm)


def _cover(photo, camera, xy_mm, r_px=30):
    out = photo.copy()
    u, v = project_points(camera, [xy_mm])[0]
    cv2.circle(out, (int(u), int(v)), r_px, (40, 40, 40), -1)
    return out


def _halo(photo, camera, xy_mm):
    """A reflection spilling over one marker: a bright blurred spot a little off its centre."""
    out = photo.astype(np.float32)
    u, v = project_points(camera, [xy_mm])[0]
    spot = np.zeros(photo.shape[:2], np.float32)
    cv2.circle(spot, (int(u) + 6, int(v) - 4), 14, 1.0, -1)
    out += 200 * cv2.GaussianBlur(spot, (0, 0), 3)[..., None]
    return np.clip(out, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("case", ["blank", "overexposed", "blurred", "occluded", "extra dot", "halo"])
def test_bad_photos_give_clear_marker_errors(camera, topview, bed_photo, case):
    if case == "blank":
        photo, match = render_bed_scene(camera, np.empty((0, 2)), 6.0, supersample=1), "found 0 of the 4"
    elif case == "overexposed":
        photo, match = render_bed_scene(camera, topview.corners_mm, 6.0, exposure=12.0, supersample=1), "overexposed"
    elif case == "blurred":
        photo, match = cv2.GaussianBlur(bed_photo, (0, 0), 25), "blurred"
    elif case == "occluded":
        photo, match = _cover(bed_photo, camera, topview.corners_mm[2]), "covered"
    elif case == "halo":
        photo, match = _halo(bed_photo, camera, topview.corners_mm[2]), "expected size|fit"
    else:
        photo = render_bed_scene(camera, np.r_[topview.corners_mm, [[0.0, 0.0]]], 6.0, supersample=1)
        photo = _cover(photo, camera, topview.corners_mm[3])  # 4 dots seen, one of them wrong
        match = "fit"
    with pytest.raises(MarkerError, match=match):
        locate_bed(_unposed(camera), photo, MarkerSettings(), topview)


def test_duplicated_marker_is_refused(camera, topview):
    """Six dots holding two equally good rectangles of the layout: refuse, do not guess."""
    layout = [(-50.0, -35.0), (0.0, -35.0), (0.0, 35.0), (-50.0, 35.0)]
    dots = [(x, y) for x in (-50.0, 0.0, 50.0) for y in (-35.0, 35.0)]
    photo = render_bed_scene(camera, dots, 6.0, supersample=1, bed_center_mm=(0, 0))
    with pytest.raises(MarkerError, match="more bright dots"):
        locate_bed(_unposed(camera), photo, MarkerSettings(positions_mm=layout), topview)
    # with the extra dots covered the same photo is fine
    for xy in dots[4:]:
        photo = _cover(photo, camera, xy)
    est = locate_bed(_unposed(camera), photo, MarkerSettings(positions_mm=layout), topview)
    assert np.linalg.norm(est.center_mm - camera.center_mm) <= 1.0


def test_model_from_another_resolution(camera, topview, bed_photo):
    hi = camera.scaled_to((1920, 1080))
    est = locate_bed(_unposed(hi), bed_photo, MarkerSettings(), topview)
    assert est.image_size == (1920, 1080)
    assert np.linalg.norm(est.center_mm - camera.center_mm) <= 1.0
    with pytest.raises(LayerwatchError, match="aspect ratio"):
        locate_bed(_unposed(camera.scaled_to((640, 480))), bed_photo, MarkerSettings(), topview)


def test_camera_moved_check(camera, topview, bed_photo, caplog):
    saved = locate_bed(_unposed(camera), bed_photo, MarkerSettings(), topview)
    ok = camera_moved(saved, bed_photo, MarkerSettings(), topview)
    assert not ok.moved and ok.shift_px < 1.0
    nudged = posed_camera(eye=(8.0, -170.0, 190.0))
    photo = render_bed_scene(nudged, topview.corners_mm, 6.0, supersample=1, seed=9)
    with caplog.at_level("WARNING"):
        moved = camera_moved(saved, photo, MarkerSettings(), topview)
    assert moved.moved and moved.shift_px > 5 and "recalibrate" in moved.message
    assert "moved" in caplog.text
    gone = camera_moved(saved, np.zeros_like(bed_photo))
    assert gone.moved


def test_projection_without_a_full_pose_names_the_fix(camera):
    """``CameraModel.pose`` (what projection and the warp use) refuses a model missing either
    half of its pose with the calibrate hint, never a TypeError on None."""
    rvec, tvec = camera.pose
    assert rvec.shape == (3,) and tvec.shape == (3,)
    for half in ({"rvec": None}, {"tvec": None}, {"rvec": None, "tvec": None}):
        cam = replace(camera, **half)
        with pytest.raises(CalibrationError, match="no bed pose yet"):
            project_points(cam, np.zeros((1, 3)))
