"""Camera-view photos: parallax is physical, determinism by seed, markers visible."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.simulate import simulate_layer, simulate_print
from layerwatch.simulate.raster import solid_area


def _warp_plane(photo, camera, topview, z):
    """Independent top view of plane ``z``: undistort, then K [r1 r2 r3 z + t] homography."""
    und = cv2.undistort(photo, camera.K, camera.dist)
    R, t = camera.R, camera.tvec
    img_from_bed = camera.K @ np.column_stack([R[:, 0], R[:, 1], R[:, 2] * z + t])
    img_from_top = img_from_bed @ topview.bed_from_top
    h, w = topview.shape
    return cv2.warpPerspective(und, img_from_top, (w, h), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)


def _filament(top_bgr):
    b, r = top_bgr[..., 0].astype(int), top_bgr[..., 2].astype(int)
    return (r - b) > 60


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


def test_warp_of_top_plane_aligns_top_layer_only(tall_part, camera, topview):
    top = tall_part.n_layers - 1
    fr = simulate_layer(tall_part, top, camera, topview, seed=3)
    sl = tall_part.layer_slice(top)
    area = solid_area(tall_part.start[sl], tall_part.end[sl], tall_part.width[sl] / 2, topview)
    z_top = tall_part.layers[top].z
    at_top = _filament(_warp_plane(fr.photo, camera, topview, z_top))
    at_bed = _filament(_warp_plane(fr.photo, camera, topview, 0.0))
    # the top surface lands on the footprint; only the side wall facing the camera spills out
    assert (at_top & area).sum() >= 0.9 * area.sum()
    iou_top, iou_bed = _iou(at_top, area), _iou(at_bed, area)
    assert iou_top > 0.7
    assert iou_top > iou_bed + 0.15, (iou_top, iou_bed)
    # the far edge of the part: at z_top it is where the plan says; at z = 0 it is displaced
    rows_top = np.flatnonzero((at_top & area).any(1))
    rows_bed = np.flatnonzero(at_bed.any(1))
    rows_area = np.flatnonzero(area.any(1))
    assert abs(rows_top[0] - rows_area[0]) <= 3
    assert rows_bed[0] < rows_area[0] - 0.5 * z_top * topview.px_per_mm


def test_determinism_and_noise(part, camera, topview):
    a = simulate_layer(part, 4, camera, topview, seed=11)
    b = simulate_layer(part, 4, camera, topview, seed=11)
    c = simulate_layer(part, 4, camera, topview, seed=12)
    assert a.photo.dtype == np.uint8 and a.photo.shape == (360, 640, 3)
    assert np.array_equal(a.photo, b.photo)
    assert not np.array_equal(a.photo, c.photo)
    assert a.truth is None and a.meta["failures"] == [] and not a.meta["failed"]
    frames = list(simulate_print(part, camera, topview, seed=11, layers=[3, 4]))
    assert [f.layer for f in frames] == [3, 4]
    assert np.array_equal(frames[1].photo, a.photo)  # incremental == from scratch
    # consecutive clean layers are not pixel-identical (imperfections, light, noise)
    diff = np.abs(frames[0].photo.astype(int) - frames[1].photo.astype(int))
    assert diff.mean() > 1.0


def test_markers_are_bright_dots(part, camera, topview):
    fr = simulate_layer(part, 2, camera, topview)
    grey = cv2.cvtColor(fr.photo, cv2.COLOR_BGR2GRAY)
    uv = cv2.projectPoints(
        np.c_[camera.markers_mm, np.zeros(len(camera.markers_mm))],
        camera.rvec, camera.tvec, camera.K, camera.dist,
    )[0].reshape(-1, 2)
    w, h = camera.image_size
    for u, v in np.round(uv).astype(int):
        assert 0 <= u < w and 0 <= v < h
        assert grey[v, u] > 180
        assert np.median(grey[max(v - 40, 0) : v + 40, max(u - 40, 0) : u + 40]) < 150


def test_markers_found_by_locate_bed(part, camera, topview):
    pose = pytest.importorskip("layerwatch.geometry.pose")
    from layerwatch.geometry.settings import MarkerSettings

    fr = simulate_layer(part, 2, camera, topview)
    cam = pose.locate_bed(camera, fr.photo, MarkerSettings(), topview)
    assert np.allclose(cam.center_mm, camera.center_mm, atol=3.0)


def test_clean_frame_differs_from_reference_but_aligns(part, camera, topview):
    fast = pytest.importorskip("layerwatch.render.fast")
    idx = 6
    fr = simulate_layer(part, idx, camera, topview, seed=5)
    ref = fast.render_layer(part, idx, topview)
    top = cv2.cvtColor(_warp_plane(fr.photo, camera, topview, part.layers[idx].z), cv2.COLOR_BGR2GRAY)
    assert not np.array_equal(top, ref.image)
    sl = part.layer_slice(idx)
    area = solid_area(part.start[sl], part.end[sl], part.width[sl] / 2, topview)
    seen = _filament(_warp_plane(fr.photo, camera, topview, part.layers[idx].z))
    assert _iou(seen & area, ref.mask | area) > 0.85


def test_top_view_warper_lines_up_the_top_layer(tall_part, camera, topview):
    warp = pytest.importorskip("layerwatch.geometry.warp")
    top = tall_part.n_layers - 1
    fr = simulate_layer(tall_part, top, camera, topview, seed=3)
    sl = tall_part.layer_slice(top)
    area = solid_area(tall_part.start[sl], tall_part.end[sl], tall_part.width[sl] / 2, topview)
    img, valid = warp.TopViewWarper(camera, topview).warp(fr.photo, tall_part.layers[top].z)
    assert valid[area].all()
    seen = _filament(img) if img.ndim == 3 else None
    if seen is not None:
        assert (seen & area).sum() >= 0.9 * area.sum()
        ours = _filament(_warp_plane(fr.photo, camera, topview, tall_part.layers[top].z))
        assert _iou(seen, ours) > 0.9
