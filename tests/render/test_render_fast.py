"""Fast renderer: geometry against a NumPy brute force, shading, incremental stack, bad input."""

from __future__ import annotations

import dataclasses
import functools
import logging

import cv2
import numpy as np
import pytest
from render_parts import square_part
from render_refs import brute_capsules

from layerwatch.errors import RenderError
from layerwatch.gcode.toolpath import Layer
from layerwatch.geometry.topview import TopView
from layerwatch.render.fast import StackRenderer, render_layer, render_stack
from layerwatch.render.mask import gcode_mask
from layerwatch.render.raster import directional_light, shade_height
from layerwatch.render.settings import RenderSettings


def _mismatch(a, b):
    return np.count_nonzero(a != b) / a.size


def test_types_and_shapes(part, small_view):
    r = render_layer(part, 2, small_view)
    H, W = small_view.shape
    assert r.image.shape == (H, W) and r.image.dtype == np.uint8
    assert r.height.shape == (H, W) and r.height.dtype == np.float32
    assert r.mask.shape == (H, W) and r.mask.dtype == bool
    assert r.layer == 2 and r.z == pytest.approx(part.layers[2].z)
    assert r.rgb().shape == (H, W, 3)


@pytest.mark.parametrize("index", [0, 3])
def test_mask_matches_brute_force(part, small_view, index):
    expected = brute_capsules(part, index, small_view)
    r = StackRenderer(part, small_view).render(index)
    assert expected.sum() > 1000
    assert _mismatch(r.mask, expected) < 1e-3
    assert np.array_equal(gcode_mask(part, index, small_view), r.mask)


def test_thin_wall_mask_and_height(wall, small_view):
    idx = 2
    expected = brute_capsules(wall, idx, small_view, height=True)
    r = StackRenderer(wall, small_view).render(idx)
    assert np.abs(r.height - expected).max() < 1e-4
    # one bead: about width * px_per_mm pixels across, length + width along
    area_mm2 = r.mask.sum() / small_view.px_per_mm**2
    assert area_mm2 == pytest.approx(20.0 * 0.45 + np.pi * 0.225**2, rel=0.06)
    assert r.height.max() == pytest.approx(wall.layers[idx].z, abs=0.01)


def test_height_map_matches_brute_force(part, small_view):
    r = StackRenderer(part, small_view).render(1)
    expected = brute_capsules(part, 1, small_view, height=True)
    close = np.abs(r.height - expected) < 1e-4
    assert close.mean() > 0.999


def test_incremental_equals_fresh(part, small_view):
    sr = StackRenderer(part, small_view)
    seq = [sr.render(i) for i in range(4)]
    for i in (1, 3):
        fresh = StackRenderer(part, small_view).render(i)
        assert np.array_equal(seq[i].image, fresh.image)
        assert np.array_equal(seq[i].height, fresh.height)
        assert np.array_equal(seq[i].mask, fresh.mask)
    # going back restarts; asking the same layer twice gives the same result
    again = sr.render(1)
    assert np.array_equal(again.image, seq[1].image) and np.array_equal(again.mask, seq[1].mask)
    same = sr.render(1)
    assert np.array_equal(same.mask, seq[1].mask)
    stacked = list(render_stack(part, small_view, layers=[3, 1]))
    assert [s.layer for s in stacked] == [1, 3]
    assert np.array_equal(stacked[1].image, seq[3].image)
    # module-level render_layer, decreasing then increasing
    assert np.array_equal(render_layer(part, 3, small_view).image, seq[3].image)
    assert np.array_equal(render_layer(part, 0, small_view).image, seq[0].image)


def _dominant_orientation(img, mask):
    g = img.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1)
    jxx, jyy, jxy = (gx * gx)[mask].sum(), (gy * gy)[mask].sum(), (gx * gy)[mask].sum()
    ang = 0.5 * np.degrees(np.arctan2(2 * jxy, jxx - jyy))  # gradient direction, image frame
    coherence = np.hypot(jxx - jyy, 2 * jxy) / (jxx + jyy)
    return ang, coherence


def test_infill_direction_visible(part, small_view):
    """Alternate layers have +-45 deg infill: gradients must turn by 90 deg."""
    sr = StackRenderer(part, small_view)
    inner = np.zeros(small_view.shape, bool)
    c = small_view.to_px(np.array([5.0, -3.0])).round().astype(int)
    inner[c[1] - 40 : c[1] + 40, c[0] - 40 : c[0] + 40] = True
    a0, c0 = _dominant_orientation(sr.render(0).image, inner)
    a1, c1 = _dominant_orientation(sr.render(1).image, inner)
    assert c0 > 0.3 and c1 > 0.3
    assert abs(abs(a0 - a1) - 90) < 15
    assert min(abs(abs(a0) - 45), abs(abs(a1) - 45)) < 15


def test_lower_layer_darker_in_gaps_and_bed_colour(small_view):
    # solid first layer, sparse (2 mm) infill on top: the first layer shows through
    solid = square_part(1, center=(5.0, -3.0), size=20.0)
    sparse = square_part(2, center=(5.0, -3.0), size=20.0, infill_spacing=2.0)
    n0 = solid.layers[0].n_segments
    s1 = sparse.layer_slice(1)
    from layerwatch.gcode.toolpath import Toolpath

    tp = Toolpath.from_segments(
        np.concatenate([solid.start[:n0], sparse.start[s1]]),
        np.concatenate([solid.end[:n0], sparse.end[s1]]),
        np.concatenate([solid.z[:n0], sparse.z[s1]]),
        0.45,
        layer_height=0.3,
    )
    s = RenderSettings()
    r = render_layer(tp, 1, small_view, s)
    top = r.mask & (r.height > tp.layers[1].z - 0.01)  # bead crests
    gap = (r.height > 0) & (r.height < tp.layers[0].z + 0.01) & (r.height > tp.layers[0].z - 0.05)
    assert top.sum() > 200 and gap.sum() > 200
    # the same surface is darker once a layer lies on top of it
    r0 = StackRenderer(tp, small_view, s).render(0)
    assert np.median(r.image[gap]) < np.median(r0.image[gap]) - 15
    # fewer layers visible below: the same depth is darker
    deeper = RenderSettings(layers_visible_below=1)
    assert np.median(render_layer(tp, 1, small_view, deeper).image[gap]) < np.median(r.image[gap]) - 10
    bed_grey = float(np.asarray(s.bed_rgb) @ [0.299, 0.587, 0.114]) * 255
    assert abs(int(r.image[0, 0]) - bed_grey) <= 1
    assert np.median(r.image[gap]) > bed_grey


def test_markers_drawn(part):
    tv = TopView(6.67, 60.0, 60.0, (5.0, -3.0))
    s = RenderSettings(markers_mm=[(-20.0, -28.0)], marker_diameter_mm=4.0)
    r = StackRenderer(part, tv, s).render(0)
    u, v = tv.to_px(np.array([-20.0, -28.0])).round().astype(int)
    assert r.image[v, u] > 200
    assert r.image[v, u + 30] < 60


def test_directional_light_differs(part, small_view):
    ring = StackRenderer(part, small_view).render(0).image
    d = StackRenderer(part, small_view, RenderSettings(light="directional")).render(0).image
    assert not np.array_equal(ring, d)


def test_empty_layer_defined(part, small_view):
    last = part.layers[-1]
    empty = Layer(last.index + 1, last.z + 0.3, 0.3, last.seg_stop, last.seg_stop, 0, 0,
                  (float("nan"),) * 4, 0.0)
    tp = dataclasses.replace(part, layers=(*part.layers, empty))
    r = StackRenderer(tp, small_view).render(empty.index)
    prev = StackRenderer(part, small_view).render(last.index)
    assert not r.mask.any()
    assert np.array_equal(r.height, prev.height)
    assert not gcode_mask(tp, empty.index, small_view).any()


def test_bad_index_and_no_layers(part, small_view):
    with pytest.raises(RenderError, match="does not exist"):
        render_layer(part, 99, small_view)
    empty = dataclasses.replace(part, layers=())
    with pytest.raises(RenderError, match="no layers"):
        render_layer(empty, 0, small_view)


def test_outside_observed_square_is_clipped_and_warned(caplog):
    tp = square_part(1, center=(12.0, 0.0), size=20.0)
    tv = TopView(6.67, 20.0, 20.0, (0.0, 0.0))
    with caplog.at_level(logging.WARNING, logger="layerwatch.render.fast"):
        r = StackRenderer(tp, tv).render(0)
    assert r.clipped > 0
    assert "clipped" in caplog.text
    assert r.mask[:, -1].all() and not r.mask[:, 0].any()


def test_shade_height_is_lamberts_law_on_slopes_and_level_ground():
    """The level-pixel shortcut gives what the per-light sum gives (NumPy reference of the same formula)."""
    rng = np.random.default_rng(5)
    height = np.zeros((40, 50), np.float32)
    height[5:30, 8:40] = 2.0  # a level top, its walls and the level bed
    height[10:20, 12:25] += np.round(rng.random((10, 13)), 1).astype(np.float32)  # rough patch
    lights = np.array([directional_light(a, 40.0)[0] for a in (0, 120, 240)] + [[0.0, 0.0, 1.0]])
    out = np.empty_like(height)
    shade_height(height, 2.4, 3.0, lights, 0.3, 0.6, 0.2, out)
    p = np.pad(height.astype(np.float64), 1, mode="edge")
    gx = (p[1:-1, 2:] - p[1:-1, :-2]) * 0.5 * 3.0
    gy = -(p[2:, 1:-1] - p[:-2, 1:-1]) * 0.5 * 3.0
    nz = 1.0 / np.sqrt(gx**2 + gy**2 + 1.0)
    n = np.stack([-gx * nz, -gy * nz, nz], -1)
    diff = np.clip(n @ lights.T, 0.0, None).sum(-1)
    flat = np.clip(lights[:, 2], 0, None).mean()
    light = np.minimum(0.3 + 0.7 * diff / (len(lights) * flat), 1.0)
    depth = np.clip(2.4 - height, 0.0, None)
    light = np.where(height > 0, light * (1.0 - 0.2 * np.minimum(depth / 0.6, 1.0)), light)
    np.testing.assert_allclose(out, light, rtol=0, atol=1e-6)
    assert (out == out[0, 0]).sum() > 0.5 * out.size  # most of it is level


@functools.cache
def _shade_pixels_kernel():
    """render.raster.shade_height as it was, a pixel at a time with ``_lambert`` (the reference for the
    row-at-a-time kernel; compiled once from this frozen copy)."""
    from numba import njit

    from layerwatch.render.raster import _lambert

    @njit(cache=False)
    def kernel(height, z_top, px_per_mm, lights, ambient, depth_scale, depth_dark, out):  # pragma: no cover - jit
        H, W = height.shape
        k = lights.shape[0]
        flat = 0.0
        for j in range(k):
            flat += max(lights[j, 2], 0.0)
        flat = max(flat / k, 1e-6)
        half_s = 0.5 * px_per_mm
        level = _lambert(0.0, 0.0, lights, ambient, k, flat)
        for v in range(H):
            vm = max(v - 1, 0)
            vp = min(v + 1, H - 1)
            for u in range(W):
                um = max(u - 1, 0)
                up = min(u + 1, W - 1)
                gx = (height[v, up] - height[v, um]) * half_s * (2.0 / max(up - um, 1))
                gy = -(height[vp, u] - height[vm, u]) * half_s * (2.0 / max(vp - vm, 1))
                light = level if gx == 0.0 and gy == 0.0 else _lambert(gx, gy, lights, ambient, k, flat)
                h = height[v, u]
                if h > 0.0:
                    depth = z_top - h
                    if depth < 0.0:
                        depth = 0.0
                    if depth_scale > 0.0:
                        f = depth / depth_scale
                        if f > 1.0:
                            f = 1.0
                    else:
                        f = 1.0 if depth > 1e-4 else 0.0
                    light *= 1.0 - depth_dark * f
                out[v, u] = light

    return kernel


def test_shade_height_a_row_at_a_time_equals_the_pixel_at_a_time_kernel_bit_for_bit():
    """The row-at-a-time shading (lights over the row in vectorised loops) gives the values of the kernel it
    replaced, float for float: rough and smooth height maps, level tops and bed, steep walls, depth below and
    above ``z_top``, no depth scale, lights below the horizon, odd and one-pixel-wide maps."""
    from layerwatch.render.raster import ring_lights

    rng = np.random.default_rng(21)
    smooth = cv2.GaussianBlur((rng.random((90, 77)) * 4).astype(np.float32), (0, 0), 2.0)
    rough = np.round(rng.random((64, 81)) * 3, 1).astype(np.float32)
    walls = np.zeros((50, 60), np.float32)
    walls[10:40, 12:50] = 2.0
    walls[20:30, 20:30] = 5.5
    below = np.array([[0.3, 0.1, -0.2], [0.0, 0.6, 0.8], [-0.5, 0.0, 0.866]])
    lights_sets = [ring_lights(45.0), ring_lights(20.0, 5), below, np.array([[0.0, 0.0, 1.0]])]
    cases = [(smooth, 2.5, 6.0, 0.3, 0.6, 0.2), (rough, 1.0, 3.0, 0.0, 0.0, 0.5), (walls, 2.4, 3.0, 0.25, 0.4, 0.3),
             (walls, 6.0, 1.5, 1.0, -1.0, 0.2), (smooth[:, :1].copy(), 2.0, 3.0, 0.3, 0.6, 0.2),
             (smooth[:1].copy(), 2.0, 3.0, 0.3, 0.6, 0.2), (np.zeros((7, 9), np.float32), 0.2, 3.0, 0.3, 0.6, 0.2)]
    for lights in lights_sets:
        for height, *args in cases:
            want, got = np.full_like(height, np.nan), np.full_like(height, np.nan)
            _shade_pixels_kernel()(height, *args[:2], lights, *args[2:], want)
            shade_height(height, *args[:2], lights, *args[2:], got)
            assert np.array_equal(got, want), (height.shape, args, lights.shape)
