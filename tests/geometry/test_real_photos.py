"""Real printer photos (no bed markers): the geometry stage refuses them cleanly, never crashes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.errors import LayerwatchError
from layerwatch.geometry.calibration import approximate_intrinsics
from layerwatch.geometry.pose import camera_moved, locate_bed
from layerwatch.geometry.settings import MarkerSettings
from layerwatch.geometry.warp import TopViewWarper


def test_real_photos_never_crash(shared_data, topview, camera):
    photos = sorted((shared_data / "photos").glob("*.jpg"))[:8]
    if not photos:
        pytest.skip("no real photos in the shared data")
    for path in photos:
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        assert img is not None, path
        cam = approximate_intrinsics((img.shape[1], img.shape[0]))
        try:
            posed = locate_bed(cam, img, MarkerSettings(), topview)
        except LayerwatchError as exc:
            assert str(exc) and "\n" not in str(exc)
        else:  # a plausible pose was found on something dot-like: it must be usable
            assert posed.has_pose and posed.errors["pose_px"] <= 3.0
        check = camera_moved(camera, img)
        assert isinstance(check.moved, bool)
        try:
            top, valid = TopViewWarper(camera, topview).warp(img, 1.0)
            assert top.shape[:2] == valid.shape == topview.shape and np.all(top[~valid] == 0)
        except LayerwatchError as exc:
            assert "aspect ratio" in str(exc)
