"""The nothing-extruded check: thin layers judged with the layer before, the texture computed on the box only,
the photos' noise measured beside the print and taken out of the similarity."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import layerwatch.pipeline.checks as checks_module
from layerwatch.analysis.extrusion import (
    MIN_RELIABILITY,
    block_ncc,
    block_ncc_reliability,
    box_texture,
    highpass,
    surface_similarity,
    texture_noise_var,
)
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


def _noise(rng, shape, kind):
    """Sensor noise of std ~2 grey levels: white, correlated over ~2 px (demosaicing), or through JPEG."""
    n = rng.normal(0, 2.0, shape).astype(np.float32)
    if kind == "correlated":
        n = cv2.GaussianBlur(n, (0, 0), 1.0) * 3.0
    return n


@pytest.mark.parametrize("kind", ["white", "correlated", "jpeg"])
def test_texture_noise_var_is_the_noise_of_the_texture_whatever_its_spectrum(kind):
    """On a static, textured scene photographed twice the estimate is one photo's noise variance after the
    high pass, measured directly on the noise alone (biased low by the low quantile, never high)."""
    rng = np.random.default_rng(3)
    h, w = 256, 384
    scene = 110 + 40 * cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 1.5)  # a textured bed

    def photo(seed):
        r = np.random.default_rng(seed)
        if kind == "jpeg":
            img = np.clip(scene + r.normal(0, 2.0, (h, w)), 0, 255).astype(np.uint8)
            img = cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])[1], cv2.IMREAD_GRAYSCALE)
            return img.astype(np.float32), img.astype(np.float32) - np.clip(scene, 0, 255).round()
        n = _noise(r, (h, w), kind)
        return scene + n, n

    (a, na), (b, nb) = photo(10), photo(11)
    surface = np.zeros((h, w), bool)
    surface[64:128, 96:192] = True  # left out: 24 of the 384 blocks
    got = texture_noise_var(highpass(a), highpass(b), surface, 16)
    truth = float(np.mean([np.var(highpass(na)), np.var(highpass(nb))]))
    assert 0.6 * truth <= got <= 1.05 * truth, (got, truth)
    assert np.var(highpass(a)) > 5 * truth  # the scene's own texture is not taken for noise


def test_texture_noise_var_without_enough_clear_blocks_is_nan_and_corrects_nothing():
    rng = np.random.default_rng(4)
    a, b = (rng.normal(0, 3, (64, 64)).astype(np.float32) for _ in range(2))
    mask = np.ones((64, 64), bool)
    assert np.isnan(texture_noise_var(a, b, mask, 16))  # no block clear of the surface
    ncc, scored, rel = block_ncc_reliability(a, b, mask, 16, noise_var=float("nan"))
    assert np.all(rel == 1)
    np.testing.assert_array_equal(ncc, block_ncc(a, b, mask, 16)[0])
    np.testing.assert_array_equal(scored, block_ncc(a, b, mask, 16)[1])


def test_surface_similarity_takes_the_noise_out_of_a_faint_unchanged_surface_only():
    """A faint texture seen twice through noise (reliability 0.75): median NCC about 0.75, similarity near 1;
    a new texture (beads laid since) stays near 0; a strong texture that changed in part keeps its NCC; a texture
    as faint as the noise is lifted at most 1 / MIN_RELIABILITY times."""
    rng = np.random.default_rng(5)
    h, w = 128, 128
    faint = rng.normal(0, 3.5, (h, w)).astype(np.float32)
    mask = np.ones((h, w), bool)

    def judged(x, y, noise_var):
        ncc, scored, rel = block_ncc_reliability(x, y, mask, 16, noise_var=noise_var)
        return float(np.median(ncc[scored])), surface_similarity(ncc, rel, scored)

    n1, n2 = (rng.normal(0, 2.0, (h, w)).astype(np.float32) for _ in range(2))
    raw, sim = judged(faint + n1, faint + n2, 4.0)
    assert raw < 0.8 and sim > 0.9
    raw, sim = judged(faint / 1.75 + n1, faint / 1.75 + n2, 4.0)  # signal variance = noise variance
    assert raw < 0.6 and sim == pytest.approx(raw / MIN_RELIABILITY, rel=1e-5)
    new = rng.normal(0, 3.5, (h, w)).astype(np.float32)
    assert abs(judged(faint + n1, new + n2, 4.0)[1]) < 0.2
    strong = 10 * faint
    half = strong.copy()
    half[:, ::2] = 10 * new[:, ::2]  # half the texture replaced
    raw, sim = judged(strong + n1, half + n2, 4.0)
    assert abs(sim - raw) < 0.02 and sim < 0.8


@pytest.mark.slow
def test_a_faint_run_on_the_part_is_caught_once_the_noise_is_taken_out(monkeypatch):
    """A run on the example part (tuning seed 1, its run 136: onset 13) whose top surface is faint: its median NCC
    stayed under the old threshold; with the noise measured beside the print the run's second layer is caught,
    and without it (noise estimate switched off) the same photos are not."""
    from layerwatch.examples import PART_GCODE

    tp = read_toolpath(PART_GCODE.read_bytes())
    tv, cam = _setup(tp, (1280, 720))
    fpf = _pipeline_footprints(tp, cam, tv)
    onset = 13
    out = _judge(tp, tv, cam, fpf, [Failure("nothing_extruded", onset=onset)], range(onset - 2, onset + 2), 286)
    assert not any(out[i][0].failed_check for i in (onset - 2, onset - 1))
    res, (sim, _), _ = out[onset + 1]
    assert res.failed_check == NOTHING_EXTRUDED and sim >= 0.88, sim
    monkeypatch.setattr(checks_module, "texture_noise_var", lambda *a, **k: float("nan"))
    out = _judge(tp, tv, cam, fpf, [Failure("nothing_extruded", onset=onset)], range(onset - 2, onset + 2), 286)
    assert not out[onset + 1][0].failed_check and out[onset + 1][1][0] < 0.84
