"""HOG block tensor vs skimage.feature.hog (independent implementation)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from layerwatch.analysis.hog import BLOCK_NORMS, hog_blocks
from layerwatch.errors import AnalysisError

skfeature = pytest.importorskip("skimage.feature")


def _sk(image, cell=8, block=2, bins=9, norm="L2-Hys", gamma=False, channel_axis=None):
    out = skfeature.hog(
        image,
        orientations=bins,
        pixels_per_cell=(cell, cell),
        cells_per_block=(block, block),
        block_norm=norm,
        transform_sqrt=gamma,
        feature_vector=False,
        channel_axis=channel_axis,
    )
    return out.reshape(out.shape[0], out.shape[1], -1)


def _real_greys(shared_data, n=3):
    import cv2

    paths = sorted((shared_data / "photos").glob("*.jpg"))[:n]
    if not paths:
        pytest.skip("no photos in shared data")
    return [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)[:240, :320] for p in paths]


@pytest.mark.parametrize("norm", BLOCK_NORMS)
def test_random_images_match_skimage(norm):
    rng = np.random.default_rng(0)
    for img in (rng.integers(0, 256, (70, 93), dtype=np.uint8), rng.random((61, 80))):
        ours = hog_blocks(img, block_norm=norm)
        assert ours.shape == (img.shape[0] // 8 - 1, img.shape[1] // 8 - 1, 36)
        np.testing.assert_allclose(ours, _sk(img, norm=norm), rtol=0, atol=1e-6)


@pytest.mark.parametrize("norm", BLOCK_NORMS)
def test_real_photos_match_skimage(shared_data, norm):
    for img in _real_greys(shared_data):
        np.testing.assert_allclose(hog_blocks(img, block_norm=norm), _sk(img, norm=norm), rtol=0, atol=1e-6)


@pytest.mark.parametrize(("cell", "block", "bins", "gamma"), [(4, 2, 9, False), (5, 3, 7, True), (6, 1, 12, False)])
def test_other_parameters_match_skimage(cell, block, bins, gamma):
    img = np.random.default_rng(1).integers(0, 256, (64, 75), dtype=np.uint8)
    ours = hog_blocks(img, cell_px=cell, block_cells=block, bins=bins, gamma=gamma)
    assert ours.shape[2] == block * block * bins
    np.testing.assert_allclose(ours, _sk(img, cell, block, bins, gamma=gamma), rtol=0, atol=1e-6)


def test_colour_uses_dominant_channel_like_skimage_and_ignores_channel_order():
    img = np.random.default_rng(2).integers(0, 256, (48, 56, 3), dtype=np.uint8)
    ours = hog_blocks(img)
    np.testing.assert_allclose(ours, _sk(img, channel_axis=-1), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(ours, hog_blocks(img[..., ::-1]))  # BGR == RGB


def test_energy_and_flat_images():
    flat = np.full((32, 32), 200, np.uint8)
    blocks, energy = hog_blocks(flat, return_energy=True)
    assert not blocks.any() and not energy.any()  # featureless: all-zero blocks
    step = np.zeros((32, 32), np.uint8)
    step[:, 16:] = 100
    blocks, energy = hog_blocks(step, return_energy=True)
    # a vertical edge: 2 px per row with |g| = 100 in the cell pair at columns 8-23
    assert energy.max() == pytest.approx(100 * 2 * 16 / 256)
    assert np.all(np.linalg.norm(blocks, axis=2) <= 1 + 1e-12)


@pytest.mark.parametrize(
    "bad",
    [np.zeros((8, 8)), np.full((32, 32), np.nan), np.zeros((32, 32), bool), np.zeros((4, 32, 32, 2))],
)
def test_bad_images_raise(bad):
    with pytest.raises(AnalysisError):
        hog_blocks(bad)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
@pytest.mark.parametrize("bins", [2, 4, 8, 9])
def test_gradients_exactly_on_bin_edges_match_skimage(dtype, bins):
    """Ramps and steps put gradients at exactly 0/45/90/135 degrees: edges for 2, 4 and 8 bins."""
    r, c = np.mgrid[0:40, 0:48]
    rng = np.random.default_rng(bins)
    img = np.where(r < 20, r + c, 3 * (c // 6)) + (r > 30) * 10 + rng.integers(0, 2, r.shape) * (c > 40)
    img = img.astype(dtype)
    ours = hog_blocks(img, cell_px=8, bins=bins)
    np.testing.assert_allclose(ours, _sk(img, bins=bins), rtol=0, atol=1e-6)


def _edge(angle_deg: float, size: int = 64) -> np.ndarray:
    """A straight dark-to-bright edge through the centre, at ``angle_deg`` from the image's columns, blurred."""
    r, c = np.mgrid[0:size, 0:size].astype(np.float64) - size / 2 + 0.5
    t = np.deg2rad(angle_deg)
    d = c * np.cos(t) + r * np.sin(t)  # signed distance along the gradient direction
    return (60.0 + 140.0 / (1.0 + np.exp(-d / 0.8))).astype(np.float32)


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def test_an_edge_along_the_columns_still_matches_when_it_tilts_by_a_fraction_of_a_degree():
    # one bin per vote: the straight edge's gradient (exactly 0 degrees, as a rendered reference
    # draws it) votes into the first bin, the same edge turned by -0.5 degrees (179.5) into the
    # last: the two blocks share nothing
    straight, tilted = _edge(0.0), _edge(-0.5)

    def cos(votes):
        return _cos(*[hog_blocks(im, 8, 2, 9, votes=votes)[3:5, 3:5] for im in (straight, tilted)])

    assert cos("one_bin") < 0.3
    assert cos("split_ties") > 0.65  # the straight edge's votes are half in each bin
    assert cos("interpolated") > 0.95
    # an edge along the rows (gradient at 90 degrees, mid-bin) was never at risk
    assert _cos(*[hog_blocks(_edge(a), 8, 2, 9)[3:5, 3:5] for a in (90.0, 89.5)]) > 0.95


def test_split_ties_moves_only_votes_exactly_at_zero_degrees():
    from layerwatch.analysis.hog import hog_cell_histograms

    rng = np.random.default_rng(3)
    noisy = rng.normal(100, 20, (64, 64)).astype(np.float32)  # no gradient exactly at 0 degrees inside
    a = hog_cell_histograms(noisy, 8, 9)
    b = hog_cell_histograms(noisy, 8, 9, votes="split_ties")
    assert np.array_equal(a[1:-1, 1:-1], b[1:-1, 1:-1])  # (the border rows' g_row is 0 by convention)
    straight = _edge(0.0)
    a = hog_cell_histograms(straight, 8, 9)
    b = hog_cell_histograms(straight, 8, 9, votes="split_ties")
    assert np.allclose(a.sum(2), b.sum(2), rtol=1e-6)  # nothing lost
    assert np.allclose(b[..., 0], b[..., 8], rtol=1e-5) and a[..., 8].max() == 0.0
    assert np.array_equal(a[..., 1:8], b[..., 1:8])
    colour = hog_cell_histograms(np.repeat(straight[..., None], 3, axis=2), 8, 9, votes="split_ties")
    assert np.allclose(colour, b, rtol=1e-5, atol=1e-9)
    with pytest.raises(AnalysisError):
        hog_cell_histograms(straight, 8, 9, votes="nearest")


@functools.cache
def _cells_kernel():
    """hog_kernels.hist_from_image as it was, a cell at a time with ``_bin_of`` per pixel (the reference for the
    row-at-a-time kernel; compiled once from this frozen copy)."""
    from numba import njit

    from layerwatch.analysis.hog_kernels import _bin_of

    @njit(cache=False)
    def kernel(img, cell_px, n_cr, n_cc, cos_e, sin_e, edges, out):  # pragma: no cover - jit
        h, w = img.shape
        bins = edges.size - 1
        area = cell_px * cell_px
        acc = np.zeros(bins, dtype=np.float32)
        for ci in range(n_cr):
            for cj in range(n_cc):
                acc[:] = 0.0
                for r in range(ci * cell_px, ci * cell_px + cell_px):
                    row_in = 0 < r < h - 1
                    for c in range(cj * cell_px, cj * cell_px + cell_px):
                        gr = float(img[r + 1, c]) - float(img[r - 1, c]) if row_in else 0.0
                        gc = float(img[r, c + 1]) - float(img[r, c - 1]) if 0 < c < w - 1 else 0.0
                        if gr == 0.0 and gc == 0.0:
                            continue
                        mag = np.sqrt(gr * gr + gc * gc)
                        b = _bin_of(gr, gc, mag, cos_e, sin_e, edges)
                        if b >= 0:
                            acc[b] = np.float32(np.float64(acc[b]) + mag)
                for b in range(bins):
                    out[ci, cj, b] = np.float32(np.float64(acc[b]) / area)

    return kernel


def _cells_before(img, cell_px, n_cr, n_cc, cos_e, sin_e, edges, out):
    _cells_kernel()(img, cell_px, n_cr, n_cc, cos_e, sin_e, edges, out)


def _kernel_images(dtype):
    """Images for the kernel comparisons: flat runs, straight edges along the columns, gradients on bin edges
    (ramps and steps), smooth noise, a blurred real-looking edge, sizes that leave partial cells out."""
    rng = np.random.default_rng(11)
    r, c = np.mgrid[0:40, 0:48]
    ramps = np.where(r < 20, r + c, 3 * (c // 6)) + (r > 30) * 10 + rng.integers(0, 2, r.shape) * (c > 40)
    noise = rng.normal(100, 30, (83, 101)) if dtype != np.uint16 else rng.integers(0, 4000, (83, 101))
    out = [rng.integers(0, 4, (83, 101)) * 20, noise, np.repeat(rng.integers(0, 200, (1, 101)), 83, axis=0), ramps,
           np.zeros((17, 24)), np.zeros((5, 30)), rng.integers(0, 9, (64, 8))]
    if dtype != np.uint16:
        out += [_edge(a) for a in (0.0, 20.0, 45.0, -0.5, 90.0)]
    if dtype == np.float64:
        out.append(_near_edge_stencils())
    return [np.ascontiguousarray(np.asarray(im), dtype) for im in out]


def _near_edge_stencils(bins: int = 9) -> np.ndarray:
    """A float64 image whose isolated pixels have gradients within ~1e-15 rad of a bin edge where the sign test of
    ``_bin_of`` and skimage's degree arithmetic disagree (the kernels' ``close`` fallback decides them)."""
    from layerwatch.analysis.hog import _bin_edges

    rng = np.random.default_rng(0)
    edges = _bin_edges(bins)
    ce, se = np.cos(np.deg2rad(edges)), np.sin(np.deg2rad(edges))
    th = np.repeat(np.deg2rad(edges[1:bins].astype(np.float64)), 4000) + rng.normal(0, 1e-15, 4000 * (bins - 1))
    m = rng.uniform(1, 200, th.size)
    gr, gc = m * np.sin(th), m * np.cos(th)
    count = sum((gr * ce[i] - gc * se[i] >= 0).astype(int) for i in range(1, bins))
    ang = np.arctan2(gr, gc) * (180.0 / np.pi)
    differ = count != np.searchsorted(edges, ang, side="right") - 1
    assert differ.sum() >= 5  # (the test would not reach the fallback otherwise)
    img = np.zeros((48, 48))
    for k, (a, b) in enumerate(zip(gr[differ][:25], gc[differ][:25], strict=False)):
        r, c = 2 + 4 * (k // 5), 2 + 4 * (k % 5)  # g_row = img[r+1, c] - img[r-1, c] = a, g_col = b
        img[r + 1, c], img[r, c + 1] = a, b
    return img


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16])
@pytest.mark.parametrize("bins", [9, 4, 8, 7])
def test_the_row_at_a_time_kernel_equals_the_cell_at_a_time_one_bit_for_bit(dtype, bins):
    """``hist_from_image`` (a row of pixels at a time, edge tests over the row) gives the histograms of the kernel
    it replaced (a cell at a time, :func:`_bin_of` per pixel) bit for bit, and the 0-degree votes it fills in the
    same pass (``zero``) are :func:`zero_angle_votes`' bit for bit."""
    from layerwatch.analysis.hog import _bin_edges
    from layerwatch.analysis.hog_kernels import hist_from_image, zero_angle_votes

    edges = _bin_edges(bins)
    cos_e, sin_e = np.cos(np.deg2rad(edges)), np.sin(np.deg2rad(edges))
    for img in _kernel_images(dtype):
        for cell in (8, 5):
            n_cr, n_cc = img.shape[0] // cell, img.shape[1] // cell
            want_hist, got_hist = np.zeros((n_cr, n_cc, bins)), np.full((n_cr, n_cc, bins), np.nan)
            want_zero, got_zero = np.zeros((n_cr, n_cc)), np.full((n_cr, n_cc), np.nan)
            _cells_before(img, cell, n_cr, n_cc, cos_e, sin_e, edges, want_hist)
            zero_angle_votes(img, cell, n_cr, n_cc, want_zero)
            hist_from_image(img, cell, n_cr, n_cc, cos_e, sin_e, edges, got_hist, got_zero)
            assert np.array_equal(got_hist, want_hist), (img.shape, cell)
            assert np.array_equal(got_zero, want_zero)
            assert np.array_equal(np.signbit(got_zero), np.signbit(want_zero))
            alone = np.full_like(got_hist, np.nan)
            hist_from_image(img, cell, n_cr, n_cc, cos_e, sin_e, edges, alone)  # without ``zero``: the same
            assert np.array_equal(alone, want_hist)


def test_the_row_at_a_time_kernel_on_real_photos_and_a_rendered_reference(shared_data):
    from layerwatch.analysis.hog import _bin_edges
    from layerwatch.analysis.hog_kernels import hist_from_image

    edges = _bin_edges(9)
    cos_e, sin_e = np.cos(np.deg2rad(edges)), np.sin(np.deg2rad(edges))
    import cv2

    for grey in _real_greys(shared_data):
        img = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 1.0)
        n_cr, n_cc = img.shape[0] // 8, img.shape[1] // 8
        want, got = np.zeros((n_cr, n_cc, 9)), np.zeros((n_cr, n_cc, 9))
        _cells_before(img, 8, n_cr, n_cc, cos_e, sin_e, edges, want)
        hist_from_image(img, 8, n_cr, n_cc, cos_e, sin_e, edges, got)
        assert np.array_equal(got, want)


def test_interpolated_votes_split_each_vote_between_the_two_nearest_centres():
    from layerwatch.analysis.hog import hog_cell_histograms

    for angle, expect in ((10.0, {0: 1.0}), (20.0, {0: 0.5, 1: 0.5}), (0.0, {0: 0.5, 8: 0.5}),
                          (175.0, {8: 0.75, 0: 0.25}), (95.0, {4: 0.75, 5: 0.25})):
        img = _edge(angle, 96)
        h = hog_cell_histograms(img, 8, 9, votes="interpolated")[5:7, 5:7].sum(axis=(0, 1))
        hard = hog_cell_histograms(img, 8, 9)[5:7, 5:7].sum(axis=(0, 1))
        assert h.sum() == pytest.approx(hard.sum(), rel=1e-5)  # the magnitude is split, not changed
        share = h / h.sum()
        for b, v in expect.items():
            assert share[b] == pytest.approx(v, abs=0.06), (angle, b, share)
        assert sum(share[b] for b in expect) == pytest.approx(1.0, abs=0.06)


def test_interpolated_votes_colour_and_uint8_agree_with_grey_float():
    img = _edge(33.0)
    grey = hog_blocks(img, 8, 2, 9, votes="interpolated")
    colour = hog_blocks(np.repeat(img[..., None], 3, axis=2), 8, 2, 9, votes="interpolated")
    assert np.allclose(colour, grey, atol=1e-9)
    rounded = np.round(img)
    assert np.array_equal(hog_blocks(rounded.astype(np.uint8), 8, 2, 9, votes="interpolated"),
                          hog_blocks(rounded.astype(np.float32), 8, 2, 9, votes="interpolated"))


@pytest.mark.slow
def test_the_window_parts_wall_along_the_columns_is_no_clean_alarm_with_split_ties():
    """A clean window-part photo (simulator seed 9100, layer 15: the box's left wall beside the bridge's
    pillar) read above the pause ratio with one bin per vote: the reference's straight wall edge voted
    at exactly 0 degrees, the photo's (177-178 degrees) into the last bin. With split ties it is clean."""
    from layerwatch.examples import PART_CONFIG
    from layerwatch.pipeline.config import resolve_config
    from layerwatch.pipeline.step import LayerPipeline
    from layerwatch.simulate import PrintSimulator, default_camera
    from layerwatch.simulate.parts import window_part

    cfg = resolve_config(PART_CONFIG).config
    cam = default_camera(cfg.topview.topview(), image_size=(1280, 720))
    cfg = cfg.for_camera(cam)
    assert cfg.analysis.votes == "split_ties"  # recommended
    tp = window_part(center=(float(cfg.topview.center_mm[0]), float(cfg.topview.center_mm[1])))
    photo = PrintSimulator(tp, cam, cfg.topview.topview(), (), seed=9100).frame(15).photo
    ratio = {}
    for votes in ("one_bin", "split_ties"):
        c = cfg.model_copy(update={"analysis": cfg.analysis.model_copy(update={"votes": votes})})
        res = LayerPipeline(tp, cam, c, memo=1).process(photo, 15)
        assert res.status == "ok", res.message
        ratio[votes] = res.anomaly_ratio
    assert ratio["one_bin"] > cfg.policy.pause_ratio > 4 * ratio["split_ties"]
