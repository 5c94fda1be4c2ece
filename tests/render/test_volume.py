"""The occupancy-volume reference: windows, bridges and overhangs seen as the camera sees them."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from render_parts import square_part

from layerwatch.geometry.settings import TopViewSettings
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.render import fast
from layerwatch.render.cache import ReferenceCache
from layerwatch.render.fast import StackRenderer
from layerwatch.render.settings import RenderSettings
from layerwatch.render.volume import OccupancyStack, view_through_volume
from layerwatch.simulate import default_camera
from layerwatch.simulate.parts import blocks_part

TV = TopView(8.0, 50.0, 50.0, (0.0, 0.0))  # 400 x 400 px
CAM = np.array([0.0, -120.0, 120.0])  # in front of the printer (-Y), 45 deg


def _plane_point(p: np.ndarray, z: float) -> np.ndarray:
    """Top-view pixel of the plane ``Z = z`` whose camera ray passes through the 3-D point ``p`` (bed mm)."""
    q = CAM + (p - CAM) * (CAM[2] - z) / (CAM[2] - p[2])
    return np.round(TV.to_px(q[:2])).astype(int)


def _pair(tp, index=-1, **kw):
    s = RenderSettings(**{"image_blur_px": 0.0, **kw})
    out = []
    for ref in ("height", "volume"):
        r = StackRenderer(tp, TV, s.model_copy(update={"reference": ref}))
        out.append(r.render(index % tp.n_layers, CAM))
    return out


# a 20 mm wall along X (y -1..1), 10 mm tall, with a window x -4..4, z 3..7
WINDOW_WALL = [(-10, -1, 10, 1, 0, 3), (-10, -1, -4, 1, 3, 7), (4, -1, 10, 1, 3, 7), (-10, -1, 10, 1, 7, 10)]
# two pillars 8 mm apart spanned by a deck at 6..8 mm
BRIDGE = [(-10, -2, -6, 2, 0, 6), (6, -2, 10, 2, 0, 6), (-10, -2, 10, 2, 6, 8)]


def test_window_through_a_wall_shows_the_bed_behind_it():
    tp = blocks_part(WINDOW_WALL)
    height_ref, volume_ref = _pair(tp)
    z = tp.layers[-1].z
    bed = round(float(np.asarray(RenderSettings().bed_rgb) @ [0.299, 0.587, 0.114]) * 255)
    # the ray through the window's centre goes on behind the wall to the bed
    u, v = _plane_point(np.array([0.0, -1.0, 5.0]), z)
    assert abs(int(volume_ref.image[v, u]) - bed) <= 3
    assert int(height_ref.image[v, u]) > bed + 80  # the height map shows the wall there
    # below the window both show the same wall
    u2, v2 = _plane_point(np.array([0.0, -1.0, 1.5]), z)
    assert abs(int(volume_ref.image[v2, u2]) - int(height_ref.image[v2, u2])) <= 1
    assert int(volume_ref.image[v2, u2]) > bed + 80


def test_bed_under_a_bridge():
    tp = blocks_part(BRIDGE)
    height_ref, volume_ref = _pair(tp)
    z = tp.layers[-1].z
    bed = round(float(np.asarray(RenderSettings().bed_rgb) @ [0.299, 0.587, 0.114]) * 255)
    u, v = _plane_point(np.array([0.0, 0.0, 0.0]), z)  # the bed under the deck's middle
    assert abs(int(volume_ref.image[v, u]) - bed) <= 3
    assert int(height_ref.image[v, u]) > bed + 80
    # the deck's own top is the same in both
    u2, v2 = np.round(TV.to_px(np.array([0.0, 1.0]))).astype(int)
    assert volume_ref.image[v2, u2] == height_ref.image[v2, u2]


def test_hidden_floor_seen_through_a_window_is_darkened_with_depth():
    """A low block behind the window: the ray lands on its top (hidden from above by nothing)."""
    tp = blocks_part(WINDOW_WALL + [(-6, 1, 6, 8, 0, 2)])
    _, volume_ref = _pair(tp)
    z = tp.layers[-1].z
    # the ray through the window's lower part reaches the low block's top at z = 2
    u, v = _plane_point(np.array([0.0, 3.0, 2.0]), z)
    mat = float(np.asarray(RenderSettings().material_rgb) @ [0.299, 0.587, 0.114])
    lit = mat * (1 - RenderSettings().depth_darkening)  # far below the plane: the darkest level of lower layers
    assert int(volume_ref.image[v, u]) == pytest.approx(lit * 255, abs=3)


def test_ordinary_part_renders_as_the_height_map():
    tp = square_part(6, size=20.0)
    for index in (0, 3, 5):
        h, vol = _pair(tp, index, image_blur_px=1.0)
        assert np.array_equal(h.image, vol.image)


def test_overhang_shows_the_bed_under_it():
    tp = blocks_part([(-4, 0, 4, 6, 0, 8), (-4, -6, 4, 0, 4, 6)])  # a ledge sticking out towards the camera
    height_ref, volume_ref = _pair(tp)
    z = tp.layers[-1].z
    bed = round(float(np.asarray(RenderSettings().bed_rgb) @ [0.299, 0.587, 0.114]) * 255)
    u, v = _plane_point(np.array([0.0, -3.0, 0.0]), z)  # the bed under the ledge
    assert abs(int(volume_ref.image[v, u]) - bed) <= 3
    assert int(height_ref.image[v, u]) > bed + 80


def test_occupancy_memory_of_a_tall_part():
    """500 layers at 600 x 600 px: one bit per pixel and layer (22.5 MB), well under 200 MB."""
    z = 0.2 * (np.arange(500) + 1)
    occ = OccupancyStack((600, 600), z, np.full(500, 0.2))
    mask = np.zeros((600, 600), bool)
    mask[100:500, 100:500] = True
    for i in range(500):
        occ.add(i, mask)
    assert occ.max_nbytes == 500 * 600 * 75  # the bound, on the whole view
    assert occ.nbytes == 500 * (400 + 2 * 16) * (51 + 2 * 2)  # the printed box (bytes 12..62) and its margin only
    assert occ.nbytes < 30e6


def test_slots_follow_layer_heights_and_close_short_gaps():
    # layer 0 at 0.2 (0.2 thick), layer 1 at 0.6 (0.4 thick: fills slots 0.4 and 0.6), layer 2 at 0.4 printed later
    occ = OccupancyStack((4, 8), [0.2, 0.6, 0.4, 1.4], [0.2, 0.4, 0.2, 0.2], fill_layers=2)
    assert list(occ.tops) == [0.2, 0.4, 0.6, 1.4]
    a = np.zeros((4, 8), bool)
    a[1, 3] = True
    occ.add(1, a)
    bits = np.unpackbits(occ.full_bits(), axis=2, bitorder="little")
    assert bits[1, 1, 3] and bits[2, 1, 3] and not bits[0, 1, 3]
    b = np.zeros((4, 8), bool)
    b[2, 5] = True
    occ.add(0, b)
    occ.add(3, b)  # one empty slot (0.4..0.6... only 2 slots: 0.4 and 0.6) between 0.2 and 1.4: closed
    bits = np.unpackbits(occ.full_bits(), axis=2, bitorder="little")
    assert bits[:4, 2, 5].all()
    no_fill = OccupancyStack((4, 8), [0.2, 0.6, 0.4, 1.4], [0.2, 0.4, 0.2, 0.2], fill_layers=0)
    no_fill.add(0, b)
    no_fill.add(3, b)
    bits = np.unpackbits(no_fill.full_bits(), axis=2, bitorder="little")
    assert bits[0, 2, 5] and bits[3, 2, 5] and not bits[1, 2, 5] and not bits[2, 2, 5]


def test_reference_setting_is_validated_and_keys_the_cache():
    with pytest.raises(ValidationError):
        RenderSettings(reference="voxels")
    with pytest.raises(ValidationError):
        RenderSettings(volume_fill_layers=-1)
    h, v = RenderSettings(reference="height"), RenderSettings()
    assert v.reference == "volume"
    assert ReferenceCache.key("g", h, TV, 3) != ReferenceCache.key("g", v, TV, 3)


def test_bad_input():
    tp = blocks_part(BRIDGE)
    occ = OccupancyStack(TV.shape, [la.z for la in tp.layers], [la.height for la in tp.layers])
    height = np.zeros(TV.shape, np.float32)
    with pytest.raises(ValueError, match="above the layer plane"):
        view_through_volume(height, height, occ, height, np.array([0.0, 0.0, 1.0]), TV, 2.0)
    with pytest.raises(ValueError, match="shape"):
        view_through_volume(height, height, occ, np.zeros((3, 3), np.float32), CAM, TV, 2.0)
    with pytest.raises(ValueError, match="centre"):
        view_through_volume(height, height, occ, height, np.array([np.nan, 0.0, 50.0]), TV, 2.0)



def test_volume_too_large_falls_back_to_the_height_map(monkeypatch, caplog):
    tp = blocks_part(BRIDGE)
    monkeypatch.setattr(fast, "VOLUME_MAX_BYTES", 1000)
    sr = StackRenderer(tp, TV, RenderSettings(reference="volume"))
    assert sr.volume is None and "occupancy volume" in caplog.text
    height = StackRenderer(tp, TV, RenderSettings(reference="height"))
    last = tp.n_layers - 1
    assert np.array_equal(sr.render(last, CAM).image, height.render(last, CAM).image)


def test_pipeline_reference_and_disk_cache_follow_the_setting(tmp_path):
    tp = blocks_part(BRIDGE)
    tvs = TopViewSettings(px_per_mm=8.0, width_mm=50.0, height_mm=50.0)
    cam = default_camera(tvs.topview(), image_size=(640, 360))
    images = {}
    for ref in ("volume", "height", "volume"):  # the cache must not hand one reference's image to the other
        cfg = JobConfig(topview=tvs, render=RenderSettings(reference=ref))
        images.setdefault(ref, []).append(LayerPipeline(tp, cam, cfg, cache_dir=tmp_path).reference(tp.n_layers - 1).image)
    assert np.array_equal(images["volume"][0], images["volume"][1])
    assert np.count_nonzero(np.abs(images["volume"][0].astype(int) - images["height"][0]) > 40) > 200



@pytest.mark.parametrize("cam", [CAM, np.array([60.0, -200.0, 90.0])])
def test_final_approach_over_bare_bed_is_the_full_march_bit_for_bit(cam, monkeypatch):
    """The bare-bed shortcut (``clear_map``) changes no value: the march with it switched off (an all-zero
    clear map) gives the same image and hit heights, float for float, on windows, bridges and a camera far
    off the square."""
    from layerwatch.render import volume

    on = volume.clear_map
    for tp in (blocks_part(WINDOW_WALL), blocks_part(BRIDGE)):
        for index in (2, tp.n_layers // 2, tp.n_layers - 1):
            r = StackRenderer(tp, TV, RenderSettings(reference="volume"))
            lit = r.render(index, None).light
            z = tp.layers[index].z
            bed = np.full(TV.shape, 0.12, np.float32)
            assert on(volume.skip_map(r.height), 8, volume.approach_reach_px(8, 0.75)).any()  # it is taken
            fast_out = view_through_volume(r.height, lit, r.volume, bed, cam, TV, z)
            monkeypatch.setattr(volume, "clear_map", lambda hmax, *a: np.zeros(hmax.shape, np.uint8))
            full_out = view_through_volume(r.height, lit, r.volume, bed, cam, TV, z)
            monkeypatch.setattr(volume, "clear_map", on)
            for a, b in zip(fast_out, full_out, strict=True):
                np.testing.assert_array_equal(a, b)


def test_skip_and_clear_maps_on_the_printed_box_are_the_whole_maps():
    """``skip_map`` and ``clear_map`` given the box outside which the heights are 0 equal the whole maps: boxes
    inside, on each edge and corner, the whole view, one pixel and none; two skip sizes and reaches."""
    from layerwatch.render import volume
    from layerwatch.render.camera_view import skip_map

    rng = np.random.default_rng(13)
    H, W = 90, 110
    boxes = [(30, 50, 40, 70), (0, 20, 0, 25), (70, 90, 95, 110), (0, 90, 50, 60), (40, 41, 0, 110), (0, 90, 0, 110),
             (45, 46, 55, 56), (20, 20, 30, 60), (3, 9, 104, 110)]
    for box in boxes:
        r0, r1, c0, c1 = box
        h = np.zeros((H, W), np.float32)
        h[r0:r1, c0:c1] = np.where(rng.random((r1 - r0, c1 - c0)) < 0.6, rng.random((r1 - r0, c1 - c0)) * 4, 0.0)
        for skip in (8, 3):
            whole, boxed = skip_map(h, skip), skip_map(h, skip, box)
            assert np.array_equal(whole, boxed), (box, skip)
            for reach in (skip, skip + 3):
                assert np.array_equal(volume.clear_map(whole, skip, reach), volume.clear_map(boxed, skip, reach, box))


def test_the_march_given_the_renderers_printed_box_is_the_march_without_it():
    """The renderer passes its printed box (heights are 0 outside it) to the march: the same image and hit heights
    as without it, float for float, layer after layer."""
    for tp in (blocks_part(WINDOW_WALL), blocks_part(BRIDGE)):
        r = StackRenderer(tp, TV, RenderSettings(reference="volume"))
        for index in range(tp.n_layers):
            lit = r.render(index, None).light
            z = tp.layers[index].z
            bed = np.full(TV.shape, 0.12, np.float32)
            height = r.height
            rows, cols = np.flatnonzero(height.any(axis=1)), np.flatnonzero(height.any(axis=0))
            r0, r1, c0, c1 = r._hbox
            assert rows.size == 0 or (r0 <= rows[0] and rows[-1] < r1 and c0 <= cols[0] and cols[-1] < c1)
            boxed = view_through_volume(height, lit, r.volume, bed, CAM, TV, z, printed_box=r._hbox)
            whole = view_through_volume(height, lit, r.volume, bed, CAM, TV, z)
            for a, b in zip(boxed, whole, strict=True):
                np.testing.assert_array_equal(a, b)


def _job(source: str, shared_data):
    """The example part on its own top view, or a slicer's file on a 150 mm square at 3 px/mm around it."""
    from layerwatch.examples import PART_CONFIG, PART_GCODE
    from layerwatch.gcode import read_toolpath
    from layerwatch.pipeline.config import resolve_config

    if source == "example":
        return read_toolpath(PART_GCODE), resolve_config(PART_CONFIG).config.topview.topview()
    tp = read_toolpath((shared_data / "gcode" / source).read_bytes())
    x0, y0, x1, y1 = tp.bounds
    return tp, TopViewSettings(center_mm=((x0 + x1) / 2, (y0 + y1) / 2), width_mm=max(150.0, x1 - x0 + 30),
                               height_mm=max(150.0, y1 - y0 + 30), px_per_mm=3.0).topview()


def _whole_view(volume: OccupancyStack) -> OccupancyStack:
    """The same occupancy with its bits on the whole top view (the layout before the printed box)."""
    import copy

    whole = copy.copy(volume)
    whole.bits, whole.origin = volume.full_bits(), (0, 0)
    return whole


@pytest.mark.slow
@pytest.mark.parametrize("source", ["example", "prusaslicer-2.8.1_mini-cube_ascii.gcode",
                                    "cura-4.10.0_m83_multi-object.gcode"])
def test_bits_on_the_printed_box_render_every_layer_as_on_the_whole_view(source, shared_data):
    """The occupancy kept on the print's box (grown as layers come) gives the march the images and hit heights
    of the whole-view bits, float for float, on every layer of the example part and two slicers' files."""
    tp, tv = _job(source, shared_data)
    cam = default_camera(tv).center_mm
    r = StackRenderer(tp, tv, RenderSettings(reference="volume"))
    grew = 0
    for index in range(tp.n_layers):
        lit = r.render(index, None).light
        assert r.volume is not None
        grew += r.volume.nbytes < r.volume.full_bits().nbytes
        z = tp.layers[index].z
        bed = np.full(tv.shape, 0.12, np.float32)
        boxed = view_through_volume(r.height, lit, r.volume, bed, cam, tv, z)
        whole = view_through_volume(r.height, lit, _whole_view(r.volume), bed, cam, tv, z)
        for a, b in zip(boxed, whole, strict=True):
            np.testing.assert_array_equal(a, b, err_msg=f"layer {index}")
    assert grew == tp.n_layers  # the box was smaller than the view on every layer


@pytest.mark.slow
@pytest.mark.parametrize("source", ["example", "prusaslicer-2.8.1_mini-cube_ascii.gcode",
                                    "cura-4.10.0_m83_multi-object.gcode"])
def test_height_map_held_on_the_printed_box_renders_every_layer_as_the_whole_map(source, shared_data, monkeypatch):
    """Between renders a renderer keeps its height map on the box its capsules can reach: every layer's
    camera-view reference and height map equal those of a renderer that keeps the whole map."""
    tp, tv = _job(source, shared_data)
    cam = default_camera(tv).center_mm
    boxed = StackRenderer(tp, tv)
    whole = StackRenderer(tp, tv)
    monkeypatch.setattr(whole, "_cover", lambda *a: setattr(whole, "_hbox", (0, tv.shape[0], 0, tv.shape[1])))
    for index in [*range(tp.n_layers), tp.n_layers // 2, tp.n_layers - 1]:  # (then again from a reset)
        a, b = boxed.render(index, cam), whole.render(index, cam)
        np.testing.assert_array_equal(a.image, b.image, err_msg=f"layer {index}")
        np.testing.assert_array_equal(a.height, b.height, err_msg=f"layer {index}")
        np.testing.assert_array_equal(boxed.height, a.height)
        assert boxed._held.size < 0.6 * whole._held.size
