"""Plane homographies (eqs. 1-3) against cv2.projectPoints and cv2.findHomography."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from layerwatch.errors import CalibrationError
from layerwatch.geometry.homography import (
    apply_homography,
    image_from_plane,
    image_from_top,
    top_from_image,
)


@pytest.mark.parametrize("z", [0.0, 7.3, 55.0])
def test_eq3_equals_full_projection(camera, z):
    """K [r1 r2 r3 z + t] (X, Y, 1) == K [R | t] (X, Y, z, 1) (eq. 3 from eq. 1), checked numerically."""
    cam = replace(camera, dist=np.zeros(5))
    xy = np.random.default_rng(1).uniform(-60, 60, (40, 2))
    ref = cv2.projectPoints(np.c_[xy, np.full(40, z)], cam.rvec, cam.tvec, cam.K, None)[0].reshape(-1, 2)
    got = apply_homography(image_from_plane(cam, z), xy)
    assert np.abs(got - ref).max() < 1e-8
    # and the explicit matrix product of eq. 1
    P = cam.K @ np.c_[cam.R, cam.tvec]
    q = (P @ np.c_[xy, np.full(40, z), np.ones(40)].T).T
    assert np.allclose(q[:, :2] / q[:, 2:], got, atol=1e-8)


@pytest.mark.parametrize("z", [0.0, 20.0, 100.0])
def test_top_from_image_matches_findhomography(camera, topview, z):
    cam = replace(camera, dist=np.zeros(5))
    xy = np.random.default_rng(2).uniform(-45, 45, (60, 2))
    img = cv2.projectPoints(np.c_[xy, np.full(60, z)], cam.rvec, cam.tvec, cam.K, None)[0].reshape(-1, 2)
    top = topview.to_px(xy)
    H_ref, _ = cv2.findHomography(img, top, 0)
    H = top_from_image(cam, topview, z)
    assert np.allclose(H / H[2, 2], H_ref / H_ref[2, 2], rtol=1e-5, atol=1e-7)
    assert np.abs(apply_homography(H, img) - top).max() < 1e-6
    assert np.allclose(image_from_top(cam, topview, z) @ H / (image_from_top(cam, topview, z) @ H)[2, 2],
                       np.eye(3), atol=1e-9)


def test_homography_needs_a_pose(camera, topview):
    with pytest.raises(CalibrationError, match="calibrate --markers"):
        top_from_image(replace(camera, rvec=None, tvec=None), topview, 0.0)
