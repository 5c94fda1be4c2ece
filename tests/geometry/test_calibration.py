"""Intrinsics from synthetic chessboard photos rendered with a known K."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from geometry_scenes import DIST_TRUE, K_TRUE, _views

from layerwatch.errors import CalibrationError
from layerwatch.geometry.calibration import (
    BoardSpec,
    approximate_intrinsics,
    calibrate_intrinsics,
    find_board,
)
from layerwatch.geometry.synthetic import chessboard_texture


@pytest.fixture(scope="module")
def views():
    return _views(8)


def test_board_found_at_subpixel_accuracy(views):
    tex, A, corners = chessboard_texture(9, 6, 20.0)
    found = find_board(views[0], BoardSpec("chessboard", 9, 6, 20.0))
    assert found is not None and found[0].shape == (54, 3) and np.allclose(found[0], corners)


def test_chessboard_calibration_recovers_K(views):
    cam = calibrate_intrinsics(views, BoardSpec("chessboard", 9, 6, 20.0))
    assert cam.image_size == (640, 480) and not cam.approximate
    assert cam.errors["views"] == 8 and cam.errors["intrinsics_px"] < 0.5
    assert abs(cam.K[0, 0] / K_TRUE[0, 0] - 1) < 0.03
    assert abs(cam.K[1, 1] / K_TRUE[1, 1] - 1) < 0.03
    assert np.abs(cam.K[:2, 2] - K_TRUE[:2, 2]).max() < 10
    # the distortion is recovered well enough to straighten the image
    pts = np.array([[[20.0, 20.0]], [[620.0, 460.0]], [[600.0, 30.0]]])
    a = cv2.undistortPoints(pts, K_TRUE, DIST_TRUE, P=K_TRUE)
    b = cv2.undistortPoints(pts, cam.K, cam.dist, P=K_TRUE)
    assert np.abs(a - b).max() < 2.0


@pytest.mark.slow
def test_too_few_usable_views_are_refused(views):
    blank = np.full((480, 640, 3), 128, np.uint8)
    with pytest.raises(CalibrationError, match="found in 2 photo"):
        calibrate_intrinsics([views[0], views[1], blank, blank], BoardSpec("chessboard", 9, 6, 20.0))
    with pytest.raises(CalibrationError, match="found in 0"):
        calibrate_intrinsics(views[:3], BoardSpec("chessboard", 7, 5, 20.0))  # wrong --board-size
    with pytest.raises(CalibrationError, match="differ in size"):
        calibrate_intrinsics([views[0], blank[:240, :320]], BoardSpec("chessboard", 9, 6, 20.0))
    with pytest.raises(CalibrationError):
        BoardSpec("dartboard")


def test_approximate_intrinsics_are_flagged():
    cam = approximate_intrinsics((1920, 1080), hfov_deg=90.0)
    assert cam.approximate and np.isclose(cam.K[0, 0], 960.0) and np.allclose(cam.K[:2, 2], [959.5, 539.5])
    with pytest.raises(CalibrationError, match="field of view"):
        approximate_intrinsics((640, 480), hfov_deg=0.5)


def test_charuco_board_is_detected():
    import cv2 as _cv

    spec = BoardSpec("charuco", 7, 5, 20.0)
    img = spec.charuco().generateImage((700, 500), marginSize=20)
    found = find_board(_cv.cvtColor(img, _cv.COLOR_GRAY2BGR), spec)
    assert found is not None and len(found[0]) >= 20
