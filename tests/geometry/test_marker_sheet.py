"""The printable marker sheet (`layerwatch markers`): marks where it says, found by the project's own detector."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
from geometry_scenes import posed_camera, rotation_error_deg

from layerwatch.cli import main
from layerwatch.errors import ConfigError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.marker_sheet import SCALE_BAR_MM, plan_layout, write_sheet
from layerwatch.geometry.markers import detect_aruco, detect_dots
from layerwatch.geometry.pose import locate_bed, marker_layout
from layerwatch.geometry.synthetic import render_plane
from layerwatch.pipeline.config import load_config

DPI = 254.0  # 10 px per mm
PPM = DPI / 25.4


def _sheet_png(tmp_path, layout, **kw):
    (path, page), = write_sheet(layout, tmp_path / "sheet.png", dpi=DPI, **kw)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None
    return img, page


def test_layout_defaults_are_the_observed_square_on_the_bed_centre():
    lay = plan_layout((220, 220))
    # hand-computed: 90 mm square centred on (110, 110), corners in TopView.corners_mm order
    np.testing.assert_allclose(lay.positions_mm, [[65, 65], [155, 65], [155, 155], [65, 155]])
    assert lay.size_mm == 6.0
    small = plan_layout((100, 100))  # 90 mm would not fit: the square shrinks to leave 5 mm around
    assert small.side_mm == pytest.approx(100 - 24 - 10)
    centred = plan_layout((220, 220), bed_min_mm=(-110, -110))
    np.testing.assert_allclose(centred.positions_mm[0], [-45, -45])


def test_png_dots_are_detected_at_the_stated_bed_coordinates(tmp_path):
    lay = plan_layout((235, 235), side_mm=120, center_mm=(117.5, 110))
    img, page = _sheet_png(tmp_path, lay)
    blobs = detect_dots(img)
    assert len(blobs) >= 4
    found = np.array([b.center for b in blobs[:4]])  # the four best candidates are the marks
    want = page.pixels(lay.positions_mm, DPI)
    d = np.linalg.norm(found[:, None, :] - want[None, :, :], axis=2)
    assert sorted(np.argmin(d, axis=1)) == [0, 1, 2, 3]
    assert d.min(axis=1).max() < 0.3  # px at 10 px/mm: < 0.03 mm
    # detected pixel -> bed mm through the page geometry, against the stated coordinates
    bed = (np.c_[found[:, 0] + 0.5, page.size_mm[1] * PPM - found[:, 1] - 0.5] / PPM) - page.offset_mm
    for xy in lay.positions_mm:
        assert np.min(np.linalg.norm(bed - xy, axis=1)) < 0.05
    areas = np.array([b.area for b in blobs[:4]])  # the discs are printed at their stated 6 mm
    np.testing.assert_allclose(areas, np.pi * (3.0 * PPM) ** 2, rtol=0.02)
    assert "mark 2: X177.5 Y170" == lay.label(2)


def test_png_aruco_ids_sit_at_their_positions(tmp_path):
    lay = plan_layout((220, 220), kind="aruco")
    img, page = _sheet_png(tmp_path, lay)
    found = detect_aruco(img)
    assert sorted(found) == [0, 1, 2, 3]
    want = page.pixels(lay.positions_mm, DPI)
    for i in range(4):
        assert np.linalg.norm(found[i] - want[i]) < 0.5


def test_scale_bar_is_100_mm(tmp_path):
    img, _ = _sheet_png(tmp_path, plan_layout((220, 220)))
    black = (cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) < 128).astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(black)
    wide = [s for s in stats[1:] if s[cv2.CC_STAT_WIDTH] > 50 * PPM and s[cv2.CC_STAT_HEIGHT] < 10 * PPM]
    assert len(wide) == 1, "one bar-shaped black shape on the page"
    # bar + half a 0.3 mm tick at each end
    assert wide[0][cv2.CC_STAT_WIDTH] / PPM == pytest.approx(SCALE_BAR_MM + 0.3, abs=0.2)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["dots", "aruco"])
def test_sheet_on_the_bed_gives_the_camera_pose(tmp_path, kind):
    """Print (PNG), lay it on a dark bed, photograph at ~45 deg: calibrate's locate_bed recovers the pose."""
    lay = plan_layout((220, 220), kind=kind)
    tex, page = _sheet_png(tmp_path, lay)
    tex = tex.astype(np.float32) * 0.9 + 10  # paper is not pure white, toner not pure black
    ox, oy = page.offset_mm
    H = page.size_mm[1]
    texture_from_bed = np.array([[PPM, 0, ox * PPM - 0.5], [0, -PPM, (H - oy) * PPM - 0.5], [0, 0, 1]])
    truth = posed_camera(size=(1280, 720), hfov_deg=60, eye=(120, -140, 230), target=(110, 110, 0))
    photo = render_plane(truth, tex, texture_from_bed, background_rgb=(35, 35, 38), supersample=2)
    photo = np.clip(cv2.GaussianBlur(photo, (0, 0), 0.6) + np.random.default_rng(0).normal(0, 2, photo.shape),
                    0, 255).astype(np.uint8)
    cfg_path = tmp_path / "job.toml"
    cfg_path.write_text(lay.config_toml())
    cfg = load_config(cfg_path)
    np.testing.assert_allclose(marker_layout(cfg.markers, cfg.topview.topview()), lay.positions_mm)
    guess = CameraModel(K=truth.K, dist=truth.dist, image_size=truth.image_size)
    got = locate_bed(guess, photo, cfg.markers, cfg.topview.topview())
    assert rotation_error_deg(got, truth) < 0.2
    assert np.linalg.norm(got.center_mm - truth.center_mm) < 2.0
    assert got.errors["pose_px"] < 1.0


@pytest.mark.slow
def test_tiles_put_one_mark_per_page(tmp_path):
    lay = plan_layout((350, 350), side_mm=250)
    with pytest.raises(ConfigError, match="--tiles"):
        write_sheet(lay, tmp_path / "one.png")
    pages = write_sheet(lay, tmp_path / "t.png", dpi=DPI, tiles=True)
    assert [p.name for p, _ in pages] == ["t-1.png", "t-2.png", "t-3.png", "t-4.png"]
    for i, (path, page) in enumerate(pages):
        blobs = detect_dots(cv2.imread(str(path)))
        assert page.marks == (i,)
        assert np.linalg.norm(np.array(blobs[0].center) - page.pixels(lay.positions_mm[i], DPI)) < 0.3


def test_svg_and_pdf_are_valid_and_in_millimetres(tmp_path):
    lay = plan_layout((220, 220))
    (svg, page), = write_sheet(lay, tmp_path / "m.svg")
    root = ET.parse(svg).getroot()
    assert root.tag.endswith("svg")
    w_pt = float(root.get("width").removesuffix("pt"))
    assert w_pt * 25.4 / 72 == pytest.approx(page.size_mm[0], abs=0.01)  # A4 at 1:1
    (pdf, _), = write_sheet(lay, tmp_path / "m.pdf")
    data = pdf.read_bytes()
    assert data.startswith(b"%PDF") and b"/MediaBox [ 0 0 595.27" in data
    pages = write_sheet(lay, tmp_path / "t.pdf", tiles=True)
    assert len(pages) == 4
    assert len(re.findall(rb"/Type /Page\b(?!s)", (tmp_path / "t.pdf").read_bytes())) == 4


def test_cli_writes_sheet_and_config(tmp_path, capsys):
    out, cfg = tmp_path / "markers.png", tmp_path / "layerwatch.toml"
    assert main(["markers", "--bed", "220x220", "-o", str(out), "--config-out", str(cfg)]) == 0
    text = capsys.readouterr().out
    assert "mark 0: X65 Y65" in text and "mark 2: X155 Y155" in text
    job = load_config(cfg)
    assert job.markers.positions_mm == [(65, 65), (155, 65), (155, 155), (65, 155)]
    assert tuple(job.topview.center_mm) == (110, 110)
    assert main(["markers", "--bed", "220x220", "-o", str(out), "--config-out", str(cfg)]) == 2  # no overwrite


@pytest.mark.parametrize("args, needle", [
    (["--bed", "nanx220"], "finite"),
    (["--bed", "220"], "is not two numbers AxB"),
    (["--bed", "20x220"], "bed width 20 mm is outside"),
    (["--bed", "99999x220"], "outside"),
    (["--bed", "220x220", "--side", "300"], "do not fit the bed"),
    (["--bed", "220x220", "--side", "nan"], "finite"),
    (["--bed", "220x220", "--center", "0,0"], "do not fit the bed"),
    (["--bed", "220x220", "--size", "0"], "Invalid value for '--size'"),
    (["--bed", "220x220", "--size", "inf"], "Invalid value for '--size'"),
    (["--bed", "220x220", "--kind", "qr"], "use dots or aruco"),
    (["--bed", "220x220", "--dpi", "5000"], "--dpi"),
    (["--bed", "220x220", "--paper", "a3"], "a4 or letter"),
    (["--bed", "220x220", "--origin", "x,1"], "--origin"),
    (["--bed", "220x220", "--kind", "aruco", "--dictionary", "DICT_NOPE"], "unknown ArUco dictionary"),
])
def test_cli_refuses_bad_input_in_one_line(tmp_path, capsys, args, needle):
    rc = main(["markers", *args, "-o", str(tmp_path / "m.png")])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1 and needle in err
    assert not (tmp_path / "m.png").exists()


def test_cli_refuses_unknown_suffix_and_missing_folder(tmp_path, capsys):
    assert main(["markers", "--bed", "220x220", "-o", str(tmp_path / "m.txt")]) == 2
    assert main(["markers", "--bed", "220x220", "-o", str(tmp_path / "no" / "m.pdf")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert ".pdf, .svg or .png" in err[0] and "does not exist" in err[1]
