"""The camera's resolution on the bed and ``[topview] scale = "camera"``."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.errors import CalibrationError
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.resolution import camera_px_per_mm, local_px_per_mm
from layerwatch.geometry.settings import TopViewSettings
from layerwatch.pipeline.config import recommended_config
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import PrintSimulator
from layerwatch.simulate.scene import default_camera


def _down(f: float = 1000.0, height: float = 400.0, size=(1280, 720)) -> CameraModel:
    """A pinhole camera ``height`` mm above bed point (100, 100), looking straight down."""
    K = np.array([[f, 0, size[0] / 2], [0, f, size[1] / 2], [0, 0, 1.0]])
    R = np.diag([1.0, -1.0, -1.0])  # camera z down to the bed, image y along bed -y
    C = np.array([100.0, 100.0, height])
    rvec = np.array([np.pi, 0.0, 0.0])  # Rodrigues of diag(1, -1, -1)
    return CameraModel(K=K, dist=np.zeros(5), image_size=size, rvec=rvec, tvec=-R @ C)


def test_a_camera_looking_straight_down_resolves_focal_length_over_height():
    cam = _down(f=1000.0, height=400.0)
    assert camera_px_per_mm(cam, (100.0, 100.0), 60.0, 60.0, where="center") == pytest.approx(2.5, rel=1e-6)
    assert camera_px_per_mm(cam, (100.0, 100.0), 60.0, 60.0) == pytest.approx(2.5, rel=1e-6)
    # a plane 100 mm nearer the camera is seen finer: f / 300
    assert local_px_per_mm(cam, np.array([[100.0, 100.0]]), z=100.0)[0] == pytest.approx(1000 / 300, rel=1e-6)


def test_a_tilted_camera_is_finer_on_the_near_side_and_scales_with_the_photo_width():
    tv = TopViewSettings(center_mm=(110.0, 100.0))
    cam = default_camera(tv.topview(), image_size=(1280, 720))  # in front of the printer, looking to +y
    near, far = local_px_per_mm(cam, np.array([[110.0, 60.0], [110.0, 140.0]]))
    assert near > 1.5 * far > 0
    s720 = camera_px_per_mm(cam, tv.center_mm, tv.width_mm, tv.height_mm)
    s1080 = camera_px_per_mm(default_camera(tv.topview(), image_size=(1920, 1080)), tv.center_mm, 90.0, 90.0)
    assert s1080 == pytest.approx(1.5 * s720, rel=0.01)


def test_scale_camera_is_resolved_for_the_camera_and_fixed_is_left_alone():
    tv = TopViewSettings(center_mm=(110.0, 100.0), scale="camera")
    cam = default_camera(tv.topview(), image_size=(1920, 1080))
    got = tv.for_camera(cam)
    assert got.scale == "fixed" and got.px_per_mm == round(camera_px_per_mm(cam, (110.0, 100.0), 90.0, 90.0), 2)
    assert got.topview().shape[0] == round(90 * got.px_per_mm)
    fixed = TopViewSettings(center_mm=(110.0, 100.0))
    assert fixed.for_camera(cam) is fixed
    with pytest.raises(CalibrationError, match="pose"):
        tv.for_camera(CameraModel(K=cam.K, dist=cam.dist, image_size=cam.image_size))
    with pytest.raises(ValueError):
        TopViewSettings(scale="sensor")


def test_the_pipeline_analyses_in_the_camera_scale_top_view():
    tp = read_toolpath(PART_GCODE)
    cfg = recommended_config(PART_CONFIG)
    cfg = cfg.model_copy(update={"topview": cfg.topview.model_copy(update={"scale": "camera"})})
    cam = default_camera(cfg.topview.topview(), image_size=(960, 540))
    pipe = LayerPipeline(tp, cam, cfg)
    assert pipe.topview.px_per_mm == pipe.config.topview.px_per_mm != 6.67
    sim = PrintSimulator(tp, cam, pipe.topview, (), seed=1)
    res = pipe.process(sim.frame(3).photo, 3)
    assert res.status == "ok" and pipe.last_top.shape == pipe.topview.shape
