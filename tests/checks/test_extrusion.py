"""The nothing-extruded check: thin layers judged with the layer before, the texture computed on the box only."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.extrusion import box_texture, highpass
from layerwatch.analysis.result import LayerResult
from layerwatch.analysis.scene_change import to_working
from layerwatch.evaluate.checks import _pipeline_footprints, _setup, job_checks
from layerwatch.gcode import read_toolpath
from layerwatch.pipeline.checks import NOTHING_EXTRUDED
from layerwatch.simulate import Failure, PrintSimulator
from layerwatch.simulate.parts import window_part

CUBE = "prusaslicer-2.8.1_mini-cube_ascii.gcode"


@pytest.mark.parametrize(("photo_size", "size"), [((1920, 1080), (1280, 720)), ((1600, 900), (1280, 720)),
                                                  ((1280, 720), (1280, 720)), ((1920, 1080), (1000, 563))])
def test_box_texture_is_the_whole_image_texture_on_the_box(photo_size, size):
    rng = np.random.default_rng(1)
    photo = rng.integers(0, 256, (photo_size[1], photo_size[0], 3), dtype=np.uint8)
    whole = highpass(to_working(photo, size))
    W, H = size
    for box in [(slice(160, 544), slice(368, 912)), (slice(0, 48), slice(0, 64)),
                (slice(H - 100, H), slice(W - 80, W)), (slice(3, H - 3), slice(5, W - 5))]:
        got = box_texture(photo, size, box)
        assert got.shape == whole[box].shape
        np.testing.assert_allclose(got, whole[box], atol=1e-3)


@pytest.fixture(scope="module")
def cube(shared_data):
    tp = read_toolpath((shared_data / "gcode" / CUBE).read_bytes())
    tv, cam = _setup(tp, (1280, 720))
    return tp, tv, cam, _pipeline_footprints(tp, cam, tv)


def _judge(tp, tv, cam, footprint, failures, layers, seed):
    sim = PrintSimulator(tp, cam, tv, failures, seed=seed)
    checks = job_checks(tp, cam, tv)
    out = {}
    for i in layers:
        res = LayerResult(layer=i, z=float(tp.layers[i].z))
        checks.after_layer(res, sim.frame(i).photo, i, footprint)
        out[i] = (res, checks.similarity, getattr(checks, "pooled", False))
    return out


@pytest.mark.parametrize("onset", [10, 20])
def test_a_run_on_the_cubes_sparse_layers_is_caught_with_the_layer_before(cube, onset):
    """A 12 mm cube's sparse layers show a 0.7 mm ring of perimeters: too few blocks to judge one layer alone
    (the check before pooling judged none of them), two layers together are caught on the run's second layer."""
    tp, tv, cam, footprint = cube
    out = _judge(tp, tv, cam, footprint, [Failure("nothing_extruded", onset=onset)], range(onset - 2, onset + 2), 163)
    assert not any(out[i][0].failed_check for i in (onset - 2, onset - 1))
    res, (sim, blocks), pooled = out[onset + 1]
    assert res.failed_check == NOTHING_EXTRUDED and pooled and blocks >= 3
    assert f"layers {onset} and {onset + 1}" in res.message
    assert res.check_regions[-1].kind == NOTHING_EXTRUDED


@pytest.mark.slow
def test_clean_prints_with_thin_layers_raise_no_alarm(cube):
    """Every layer of a clean cube and of the window part (thin walls, a bridge, a window): pooled layers judged,
    none flagged."""
    tp, tv, cam, footprint = cube
    wtp = window_part()
    wtv, wcam = _setup(wtp, (1280, 720))
    judged = {}
    for name, (p, t, c, f) in {"cube": (tp, tv, cam, footprint),
                               "window": (wtp, wtv, wcam, _pipeline_footprints(wtp, wcam, wtv))}.items():
        out = _judge(p, t, c, f, [], range(p.n_layers), 11)
        assert not [i for i, (r, _, _) in out.items() if r.failed_check], name
        judged[name] = sum(1 for _, (s, _), pooled in out.values() if pooled and np.isfinite(s))
    assert judged["cube"] >= 10 and judged["window"] >= 1, judged
