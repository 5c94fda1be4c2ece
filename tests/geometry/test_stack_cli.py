"""Layer stack image (Fig. 7) and the calibrate / warp commands."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from layerwatch.cli import main
from layerwatch.errors import WarpError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.stack import layer_array, layer_stack


def _tops(n=4):
    return [np.full((60, 60, 3), 40 * k, np.uint8) for k in range(n)]


def test_layer_array_and_strip():
    tops = _tops()
    vol = layer_array(tops)
    assert vol.shape == (4, 60, 60) and vol.dtype == np.uint8 and vol[2].max() == 80
    strip = layer_stack(tops, mode="strip", size=60)
    assert strip.shape == (60, 4 * 64 - 4, 3)
    assert np.all(strip[:, 128:188] == 80)


def test_oblique_stack_draws_later_layers_on_top():
    tops = [np.full((60, 60), 50, np.uint8), np.full((60, 60), 250, np.uint8)]
    img = layer_stack(tops, size=60, spacing_px=10, squash=0.5, skew=0.0)
    assert img.dtype == np.uint8 and img.shape == (30 + 10 + 2, 62, 3)
    assert img[3, 30, 0] == 250 and img[38, 30, 0] == 50  # top sheet above, bottom sheet below
    masked = layer_stack(tops, size=60, masks=[np.zeros((60, 60), bool)] * 2)
    assert np.all(masked == 255)


def test_stack_bad_input():
    with pytest.raises(WarpError):
        layer_stack([])
    with pytest.raises(WarpError):
        layer_stack(_tops(), mode="spiral")
    with pytest.raises(WarpError, match="differ in size"):
        layer_array([np.zeros((10, 10)), np.zeros((10, 20))])


def test_calibrate_markers_then_warp_cli(tmp_path, camera, topview, bed_photo, capsys):
    bed = tmp_path / "bed.png"
    cv2.imwrite(str(bed), bed_photo)
    intr = tmp_path / "intr.toml"
    replace(camera, rvec=None, tvec=None).save(intr)
    out = tmp_path / "camera.toml"
    assert main(["calibrate", "--markers", str(bed), "--camera", str(intr), "-o", str(out)]) == 0
    cam = CameraModel.load(out)
    assert cam.has_pose and np.linalg.norm(cam.center_mm - camera.center_mm) < 1.0
    png = cv2.imread(str(out.with_suffix(".png")))
    assert png.shape == bed_photo.shape and np.any(png[..., 1] > png[..., 0] + 150)  # green square drawn
    top = tmp_path / "top.png"
    assert main(["warp", str(bed), "--camera", str(out), "--z", "0", "-o", str(top)]) == 0
    img = cv2.imread(str(top))
    assert img.shape == (600, 600, 3)
    # a white marker in each corner of the top view
    g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    assert g[2:12, 2:12].max() > 150 and g[-12:-2, -12:-2].max() > 150 and g[290:310, 290:310].max() < 150
    # without --camera the intrinsics are a flagged guess
    assert main(["calibrate", "--markers", str(bed), "--hfov", "65", "-o", str(tmp_path / "guess.json")]) == 0
    assert CameraModel.load(tmp_path / "guess.json").approximate


def test_calibrate_board_cli(tmp_path):
    from geometry_scenes import _views

    paths = []
    for k, v in enumerate(_views(4, seed=5)):
        paths.append(str(tmp_path / f"b{k}.png"))
        cv2.imwrite(paths[-1], v)
    out = tmp_path / "intr.json"
    assert main(["calibrate", "--board", *paths, "--board-size", "9x6", "--square-mm", "20", "-o", str(out)]) == 0
    cam = CameraModel.load(out)
    assert not cam.has_pose and abs(cam.K[0, 0] / 620.0 - 1) < 0.05


@pytest.mark.parametrize("args, text", [
    (["calibrate"], "nothing to do"),
    (["calibrate", "--board"], "needs photos"),
    (["calibrate", "--board", "nope.jpg"], "does not exist"),
    (["calibrate", "--markers", "BLANK"], "markers"),
    (["warp", "nope.jpg"], "does not exist"),
    (["warp", "BLANK", "--camera", "missing.toml"], "does not exist"),
])
def test_cli_errors_are_one_red_line(tmp_path, capsys, args, text):
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((360, 640, 3), 30, np.uint8))
    args = [str(blank) if a == "BLANK" else a for a in args]
    assert main(args + ["-o", str(tmp_path / "x.toml")] if args[0] == "calibrate" else args) == 2
    err = capsys.readouterr().err
    assert text in err and "Traceback" not in err
