"""The volume reference marched once per camera pixel, kept and updated layer by layer (``render.march = "image"``)."""

from __future__ import annotations

import numpy as np
import pytest
from render_parts import square_part
from test_volume import _job

from layerwatch.geometry.settings import TopViewSettings
from layerwatch.geometry.topview import TopView
from layerwatch.render.camera_image import CameraImageRays
from layerwatch.render.fast import StackRenderer
from layerwatch.render.settings import RenderSettings
from layerwatch.simulate import default_camera
from layerwatch.simulate.parts import blocks_part, window_part

TV = TopView(8.0, 50.0, 50.0, (0.0, 0.0))  # 400 x 400 px
WINDOW_WALL = [(-10, -1, 10, 1, 0, 3), (-10, -1, -4, 1, 3, 7), (4, -1, 10, 1, 3, 7), (-10, -1, 10, 1, 7, 10)]
BRIDGE = [(-10, -2, -6, 2, 0, 6), (6, -2, 10, 2, 0, 6), (-10, -2, 10, 2, 6, 8)]
IMAGE = RenderSettings(march="image")


def _check_every_layer(tp, tv, camera, layers=None):
    """Render layer by layer with kept rays; after each, the kept hits equal a from-scratch march of every ray
    and the reference equals the one shaded from those hits; returns the renderer."""
    r = StackRenderer(tp, tv, IMAGE, camera)
    assert r.rays is not None
    marched = 0
    for index in layers or range(tp.n_layers):
        r.render(index, camera.center_mm)
        scratch = r.rays.march_all(r.height, r.volume)
        np.testing.assert_array_equal(r.rays.hits, scratch, err_msg=f"layer {index}")
        marched += int(np.count_nonzero(scratch < 0x8000))
    assert marched > 0  # rays met material
    return r


@pytest.mark.parametrize("blocks", [WINDOW_WALL, BRIDGE], ids=["window", "bridge"])
def test_incremental_hits_equal_a_march_from_scratch_on_windows_and_bridges(blocks):
    """Bit for bit: each layer only marches the rays that cross what it printed, yet every ray's first hit
    is the one a march of the whole ray through the whole volume finds (windows, a bridge over a gap)."""
    tp = blocks_part(blocks)
    _check_every_layer(tp, TV, default_camera(TV))


def test_the_reference_shaded_from_kept_hits_equals_the_one_from_scratch_hits():
    """The image comes from the hits alone: shading the from-scratch hits gives the same reference, float for float."""
    tp = window_part(center=(0.0, 0.0))
    tv = TopView(6.67, 60.0, 60.0, (0.0, 0.0))
    cam = default_camera(tv)
    r = _check_every_layer(tp, tv, cam, layers=range(0, tp.n_layers, 5))
    look = np.array([0.5, 1.0, 0.2, 0.2, 0.8, 0.6, 0.2])
    lit = np.random.default_rng(0).random(tv.shape).astype(np.float32)
    bed = np.full(tv.shape, 0.12, np.float32)
    z = tp.layers[r.done].z
    kept = r.rays.camera_image(r.height, lit, bed, r.volume, z, look)
    fresh = r.rays.camera_image(r.height, lit, bed, r.volume, z, look, hits=r.rays.march_all(r.height, r.volume))
    np.testing.assert_array_equal(kept, fresh)


def test_window_shows_the_bed_behind_the_wall_as_the_plane_march_does():
    """Through the window the camera-image reference shows what the plane march shows (the bed behind the wall),
    and on the whole view the two references differ only by resampling (mean < 2 grey levels)."""
    tp = blocks_part(WINDOW_WALL)
    cam = default_camera(TV)
    img = StackRenderer(tp, TV, IMAGE, cam).render(tp.n_layers - 1, cam.center_mm).image
    plane = StackRenderer(tp, TV, RenderSettings(march="plane"), cam).render(tp.n_layers - 1, cam.center_mm).image
    d = np.abs(img.astype(int) - plane)
    assert d.mean() < 2.0
    assert np.percentile(d, 90) <= 3


@pytest.mark.slow
@pytest.mark.parametrize("source", ["example", "miraclegrue_20mm-box.gcode"])
def test_incremental_camera_image_equals_from_scratch_on_every_layer(source, shared_data):
    """The example part and a real slicer's file: on every layer the kept hits equal a march of every ray
    from scratch through the same layers, bit for bit."""
    tp, tv = _job(source, shared_data)
    cam = default_camera(tv)
    r = _check_every_layer(tp, tv, cam)
    assert r.rays.nbytes == 2 * r.rays.shape[0] * r.rays.shape[1]


def test_an_earlier_layer_starts_again_and_the_grid_is_fine_enough():
    """Asking for an earlier layer resets the kept hits (as the height map); the grid is no coarser than the
    top view on the part's box."""
    tp = square_part(4, center=(0.0, 0.0), size=20.0)
    cam = default_camera(TV)
    r = StackRenderer(tp, TV, IMAGE, cam)
    r.render(3, cam.center_mm)
    r.render(1, cam.center_mm)
    np.testing.assert_array_equal(r.rays.hits, r.rays.march_all(r.height, r.volume))
    # the grid's pixel footprint (sqrt |det J|, as ``geometry.resolution.local_px_per_mm``) is at most one
    # top-view px at the part box's corners, on the bed and at the print's top
    from layerwatch.geometry.homography import image_from_top, top_from_image
    from layerwatch.render.fast import _capsule_box, segment_pixels

    rays = r.rays
    u0, u1, v0, v1 = _capsule_box(*segment_pixels(tp, slice(0, len(tp.start)), TV), TV.shape)
    worst = 0.0
    for z in (0.0, rays.z_top):
        Ht = top_from_image(cam, TV, z) @ rays.A
        to_grid = np.linalg.inv(rays.A) @ image_from_top(cam, TV, z)
        for u, v in ((u0, v0), (u1, v0), (u0, v1), (u1, v1)):
            p = to_grid @ np.array([u, v, 1.0])
            p = p / p[2]
            q = Ht @ p
            J = (Ht[:2, :2] * q[2] - np.outer(q[:2], Ht[2, :2])) / q[2] ** 2
            worst = max(worst, float(np.sqrt(abs(np.linalg.det(J)))))
    assert 0.9 < worst <= 1.0 + 1e-6


def test_bad_camera():
    tp = square_part(2, center=(0.0, 0.0), size=10.0)
    cam = default_camera(TV)
    with pytest.raises(ValueError):
        CameraImageRays(cam, TV, (100, 200, 100, 200), z_top=float(cam.center_mm[2]) + 5.0)
    # without a camera the plane march is used
    assert StackRenderer(tp, TV, IMAGE).rays is None


@pytest.mark.slow
@pytest.mark.parametrize("source", ["example", "prusaslicer-2.8.1_mini-cube_ascii.gcode",
                                    "cura-4.10.0_m83_multi-object.gcode"])
def test_light_on_the_printed_box_equals_the_whole_view(source, shared_data):
    """The top view's light computed on the printed box grown by its reach, the level bed's elsewhere, equals
    the light computed on the whole view, float for float, on every layer."""
    tp, tv = _job(source, shared_data)
    r = StackRenderer(tp, tv, RenderSettings())
    smaller = 0
    for index in range(tp.n_layers):
        r.render(index, None)
        lay = tp.layers[index]
        lh = lay.height if lay.height > 0 else 0.2
        r._work = r.height
        box = r._shade_box()
        smaller += box is not None
        np.testing.assert_array_equal(r._light(lay.z, lh, box), r._light(lay.z, lh, None), err_msg=f"layer {index}")
        r._work = None
    assert smaller == tp.n_layers


def test_the_pipeline_gives_its_camera_to_the_renderer():
    """``render.march = "image"`` in a job's settings: the pipeline's renderer keeps camera rays, and its references
    differ from the plane march's by resampling only (same size, mean difference < 2 grey levels)."""
    from layerwatch.pipeline.config import JobConfig
    from layerwatch.pipeline.step import LayerPipeline

    tp = blocks_part(WINDOW_WALL)
    tvs = TopViewSettings(center_mm=(0.0, 0.0), width_mm=50.0, height_mm=50.0, px_per_mm=8.0)
    cam = default_camera(tvs.topview())
    refs = {}
    for march in ("plane", "image"):
        pipe = LayerPipeline(tp, cam, JobConfig(topview=tvs, render=RenderSettings(march=march)))
        assert (pipe.renderer.rays is not None) == (march == "image")
        refs[march] = pipe.reference(tp.n_layers - 1).image
    assert refs["image"].shape == refs["plane"].shape
    assert np.abs(refs["image"].astype(int) - refs["plane"]).mean() < 2.0
