"""Photoreal simulated photos (Blender Cycles): the camera's conventions, clean errors, and one print when installed."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from layerwatch.errors import RenderError
from layerwatch.geometry.camera import CameraModel
from layerwatch.render.blender import MissingBlenderError
from layerwatch.simulate import Failure, PrintSimulator, photoreal
from layerwatch.simulate.parts import window_part
from layerwatch.simulate.photoreal import blender_camera, ground_materials, open_air, scene_meshes
from layerwatch.simulate.raster import solid_area
from layerwatch.simulate.settings import SimSettings

HAS_BLENDER = shutil.which("blender") is not None


def _blender_project(view: dict, points: np.ndarray) -> np.ndarray:
    """Blender's pinhole (camera along -z, y up, lens shift in image widths, pixel centres at +0.5) in OpenCV px."""
    m = np.asarray(view["camera_to_bed"])
    p = (np.linalg.inv(m) @ np.column_stack([points, np.ones(len(points))]).T).T[:, :3]
    w, h = view["resolution"]
    k = view["lens_mm"] / view["sensor_width_mm"]
    u = w * (0.5 + k * p[:, 0] / -p[:, 2] - view["shift"][0])
    v = w * (h / (2 * w) - k * p[:, 1] / -p[:, 2] + view["shift"][1])
    return np.column_stack([u, v]) - 0.5


def test_the_blender_camera_projects_the_bed_where_the_pinhole_does(camera):
    rng = np.random.default_rng(0)
    cam = CameraModel(K=np.array([[700.0, 0, 300.0], [0, 700.0, 200.0], [0, 0, 1]]), dist=np.zeros(5),
                      image_size=camera.image_size, rvec=camera.rvec, tvec=camera.tvec)  # principal point off centre
    pts = np.column_stack([rng.uniform(-40, 40, (50, 2)), rng.uniform(0, 30, 50)])
    want, _ = cv2.projectPoints(pts, cam.rvec, cam.tvec, cam.K, np.zeros(5))
    assert np.allclose(_blender_project(blender_camera(cam), pts), want.reshape(-1, 2), atol=1e-6)


def test_the_air_under_a_lintel_stays_open_and_the_slab_over_it_is_closed():
    n, m = 12, 14
    xy = np.stack(np.meshgrid(np.arange(m) * 0.125, -np.arange(n) * 0.125), axis=-1)
    h = np.full((n, m), 3.0, np.float32)  # a block 3 mm tall ...
    h[:, 11:] = 0.0  # ... with the bed in front of it ...
    gap = np.zeros((n, m, 2), np.float32)
    gap[2:11, 4:11] = (1.0, 2.0)  # ... and air from 1 to 2 mm under part of it, open to the front (a window)
    (ground, gq, gcells), (slab, sq, scells) = scene_meshes(xy, h, gap)
    z = ground[:, 2].reshape(n, m)
    assert np.all(z[2:11, 4:11] == 1.0) and np.all(z[:2, :11] == 3.0)  # open down to the sill, solid elsewhere
    assert len(gq) == (n - 1) * (m - 1) and np.array_equal(gcells, np.arange(n * m))
    assert set(np.round(slab[:, 2], 3)) == {2.0, 3.0} and len(slab) == 2 * 9 * 7 and len(scells) == len(slab)
    # a closed shell: every edge of the slab's quads is shared by exactly two of them, in opposite directions
    e = np.concatenate([sq[:, [0, 1]], sq[:, [1, 2]], sq[:, [2, 3]], sq[:, [3, 0]]])
    assert len({tuple(x) for x in e}) == len(e) and {tuple(x) for x in e} == {tuple(x) for x in e[:, ::-1]}
    # the top faces up (counter-clockwise seen from +z), the underside down
    p = slab[sq[:, :3]]
    normal_z = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 1])[:, 2]
    assert (normal_z[:48] > 0).all() and (normal_z[48:96] < 0).all()
    assert len(scene_meshes(xy, h, None)) == 1


def test_sealed_air_is_meshed_solid_and_air_open_to_a_side_is_not():
    """Sparse infill under a top skin: pockets of air closed by the infill lines and the perimeters; no camera
    sees them, so they are solid (opened, every infill line left a deep groove in the top surface's mesh)."""
    n, m = 24, 24
    xy = np.stack(np.meshgrid(np.arange(m) * 0.125, -np.arange(n) * 0.125), axis=-1)
    h = np.zeros((n, m), np.float32)
    h[2:22, 2:16] = 4.0  # a plate 4 mm tall
    gap = np.zeros((n, m, 2), np.float32)
    gap[3:9, 3:8] = gap[3:9, 9:15] = gap[10:21, 3:15] = (1.0, 3.4)  # three pockets between infill lines
    gap[10:21, 15] = (1.0, 3.4)  # ... the third breaks through the perimeter over 11 cells: open to the bed
    gap[3:6, 15] = (1.0, 3.4)  # ... the second over 3 cells: a pinhole the grid left, not an opening
    assert not open_air(h, gap[..., 1])[3:9].any()
    assert open_air(h, gap[..., 1])[10:21, 3:16].all()
    assert open_air(h, gap[..., 1], min_opening=3)[3:6, 9:16].all()
    z = scene_meshes(xy, h, gap)[0][0][:, 2].reshape(n, m)
    assert np.all(z[3:9, 3:15] == 4.0) and np.all(z[10:21, 3:16] == 1.0)
    assert not open_air(h, np.zeros((n, m), np.float32)).any()


def test_the_bed_under_a_bridge_is_the_bed_and_the_sill_under_a_lintel_is_the_part():
    mat = np.full((4, 5), 3, np.uint8)  # the top's material: filament 3 everywhere
    mat[3] = 0  # bare bed
    ground = np.full((4, 5), 10.0)  # solid cells: the ground mesh at their top
    ground[1] = 0.0  # opened down to the bed under a bridge's deck
    ground[2] = 5.0  # opened down to a window's sill under its lintel
    ground[3] = 0.0
    got = ground_materials(mat, ground)
    assert np.all(got[[1, 3]] == 0) and np.all(got[[0, 2]] == 3)  # the bed under the deck, the part elsewhere
    assert got.dtype == mat.dtype


def test_the_photoreal_ground_under_an_overhang_has_the_beds_albedo_not_the_filaments(camera, topview, monkeypatch,
                                                                                     tmp_path):
    """The window part's ledge and bridge stand over the bed: Cycles must see the bed under them (it saw the
    filament's colour there, which a clean print showed as a change beside the print)."""
    monkeypatch.setattr(photoreal, "find_blender", lambda executable=None: "blender")  # no render is run
    sim = PrintSimulator(window_part(), camera, topview, seed=3, settings=SimSettings(renderer="blender"))
    cam = sim.cam
    assert isinstance(cam, photoreal.BlenderPhotographer)
    seen = {}

    def radiance(h, mat, layer_h, gap, light):  # the meshes Blender would get, then a black frame
        seen.update(cam._field(h, mat, gap, tmp_path))
        return np.zeros((camera.image_size[1], camera.image_size[0], 3), np.float32)

    monkeypatch.setattr(cam, "radiance", radiance)
    sim.frame(44)  # the ledge (x 19..23, y -8..-2, z 7..9) and the bridge's deck (x -19..-11, z 8..10) printed
    ground = seen["meshes"][0]
    verts = np.frombuffer(Path(ground["verts"]).read_bytes(), "<f4").reshape(-1, 3)
    albedo = np.frombuffer(Path(ground["albedo"]).read_bytes(), "<f4").reshape(-1, 4)[:, :3]
    for x0, y0, x1, y1 in ((19.5, -7.5, 22.5, -2.5), (-18.5, -2.5, -11.5, 2.5)):  # under the ledge, under the deck
        under = (verts[:, 0] > x0) & (verts[:, 0] < x1) & (verts[:, 1] > y0) & (verts[:, 1] < y1)
        assert under.sum() > 100 and np.all(verts[under, 2] == 0.0)
        assert np.allclose(albedo[under], cam._bed_albedo(verts[under, 0], verts[under, 1]), atol=1e-6)
    slab = seen["meshes"][1]  # the material over the air keeps the filament's albedo
    sv = np.frombuffer(Path(slab["verts"]).read_bytes(), "<f4").reshape(-1, 3)
    sa = np.frombuffer(Path(slab["albedo"]).read_bytes(), "<f4").reshape(-1, 4)[:, :3]
    ledge = (sv[:, 0] > 19.5) & (sv[:, 0] < 22.5) & (sv[:, 1] > -7.5) & (sv[:, 1] < -2.5)
    assert ledge.any() and np.all(sa[ledge, 0] - sa[ledge, 2] > 0.2)  # orange: red well above blue


def test_non_square_pixels_are_refused_in_one_line(camera):
    K = camera.K.copy()
    K[1, 1] *= 1.01
    cam = CameraModel(K=K, dist=camera.dist, image_size=camera.image_size, rvec=camera.rvec, tvec=camera.tvec)
    with pytest.raises(RenderError, match="square pixels"):
        blender_camera(cam)


def test_a_missing_blender_is_one_line_naming_the_install(part, camera, topview, monkeypatch):
    monkeypatch.setenv("LAYERWATCH_BLENDER", "no-such-blender-xyz")
    with pytest.raises(MissingBlenderError, match="apt-get install blender"):
        PrintSimulator(part, camera, topview, settings=SimSettings(renderer="blender"))


def _top_view(photo, camera, topview, z):
    """The photo's top view of plane ``z`` (undistort, then the plane's homography), BGR."""
    und = cv2.undistort(photo, camera.K, camera.dist)
    R, t = camera.R, camera.tvec
    img_from_top = camera.K @ np.column_stack([R[:, 0], R[:, 1], R[:, 2] * z + t]) @ topview.bed_from_top
    h, w = topview.shape
    return cv2.warpPerspective(und, img_from_top, (w, h), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)


@pytest.mark.slow
@pytest.mark.skipif(not HAS_BLENDER, reason="blender not installed")
def test_a_photoreal_print_is_posed_lit_and_shaped_like_the_raster_one(part, camera, topview):
    pose = pytest.importorskip("layerwatch.geometry.pose")
    from layerwatch.geometry.settings import MarkerSettings

    fb = [Failure("foreign_body", onset=4, size_mm=8.0, seed=1)]
    photoreal = PrintSimulator(part, camera, topview, fb, seed=2,
                               settings=SimSettings(renderer="blender", blender_samples=8, blender_threads=2))
    raster = PrintSimulator(part, camera, topview, fb, seed=2)
    bed = photoreal.bed_photo()
    assert bed.shape == (360, 640, 3) and bed.dtype == np.uint8
    # the markers are where the calibrated camera puts them: the pose recovered from them is the camera's
    posed = pose.locate_bed(camera, bed, MarkerSettings(), topview)
    assert np.allclose(posed.center_mm, camera.center_mm, atol=3.0)
    # lit as the raster is: the same lights, exposure and sensor (within a tenth)
    assert abs(float(bed.mean()) / float(raster.bed_photo().mean()) - 1.0) < 0.1
    i = 6
    fr = photoreal.frame(i)
    assert fr.truth is not None and fr.truth.any()
    # the printed top lands on its footprint in the top view of its plane
    top = _top_view(fr.photo, camera, topview, part.layers[i].z).astype(int)
    filament = (top[..., 2] - top[..., 0]) > 60
    sl = part.layer_slice(i)
    footprint = solid_area(part.start[sl], part.end[sl], part.width[sl] / 2, topview)
    inter = (filament & footprint).sum()
    assert inter / footprint.sum() > 0.6 and inter / max(filament.sum(), 1) > 0.6
    # the foreign body (a dark object) shows where the truth says it is
    grey = cv2.cvtColor(fr.photo, cv2.COLOR_BGR2GRAY)
    clean = cv2.cvtColor(PrintSimulator(part, camera, topview, seed=2, settings=photoreal.settings).frame(i).photo,
                         cv2.COLOR_BGR2GRAY)
    changed = cv2.absdiff(grey, clean) > 40
    assert changed.sum() > 50


def test_simulate_photoreal_without_blender_is_exit_2_before_any_work(monkeypatch, tmp_path, capsys):
    from layerwatch.cli import main

    monkeypatch.setenv("LAYERWATCH_BLENDER", "no-such-blender-xyz")
    assert main(["simulate", "--photoreal", "-n", "1", "-o", str(tmp_path / "sim")]) == 2
    assert "apt-get install blender" in capsys.readouterr().err
    assert not (tmp_path / "sim").exists()


@pytest.mark.slow
@pytest.mark.skipif(not HAS_BLENDER, reason="blender not installed")
def test_simulate_photoreal_writes_the_print(tmp_path):
    from layerwatch.cli import main

    out = tmp_path / "sim"
    assert main(["simulate", "--photoreal", "--samples", "2", "--width", "192", "-n", "2", "-f", "spaghetti@1",
                 "-o", str(out)]) == 0
    photos = [p for p in out.glob("*.png") if p.name != "bed.png" and not p.stem.endswith(("_truth", "_area"))]
    assert (out / "bed.png").is_file() and (out / "camera.toml").is_file()
    assert len(photos) == 2 and len(list(out.glob("*_truth.png"))) == 1  # spaghetti from layer 1 on
    assert cv2.imread(str(out / "bed.png")).shape == (108, 192, 3)
