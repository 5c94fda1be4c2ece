"""The "changed as predicted" channel (issue 18): unchanged footprint blocks on synthetic photo pairs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from layerwatch.analysis.extrusion import highpass
from layerwatch.analysis.layer_change import (
    LayerChangeSettings,
    add_unchanged,
    block_change,
    blocks_on_top,
    parallax_px,
    persistent_groups,
)
from layerwatch.analysis.result import BlockGrid, LayerResult, Region
from layerwatch.geometry.topview import TopView

H, W = 240, 320
#: the parallax of one layer: a surface one layer higher is seen 1.5 px higher in the image
SHIFT = (0.0, 1.5)
SURFACE = (slice(64, 192), slice(80, 272))  # the new layer's footprint, seen through the camera
GAP = (slice(96, 128), slice(120, 168))  # a part of it the nozzle missed


def _scene(seed: int) -> np.ndarray:
    """A grey photo: a smooth shade plus bead-like texture, uint8 (H, W)."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.normal(0, 1, (H, W)).astype(np.float32), (0, 0), 1.2)
    yy, xx = np.mgrid[0:H, 0:W]
    return np.clip(120 + 0.2 * xx + 0.1 * yy + 40 * tex / tex.std(), 0, 255).astype(np.float32)


def _shift(img: np.ndarray, d: tuple[float, float]) -> np.ndarray:
    M = np.float32([[1, 0, d[0]], [0, 1, d[1]]])
    return cv2.warpAffine(img, M, (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)


def _photo(img: np.ndarray, rng: np.random.Generator, gain: float = 1.0, offset: float = 0.0,
           noise: float = 2.0) -> np.ndarray:
    return np.clip(gain * img + offset + rng.normal(0, noise, img.shape), 0, 255).astype(np.uint8)


def _masks() -> tuple[np.ndarray, np.ndarray]:
    surface = np.zeros((H, W), bool)
    surface[SURFACE] = True
    near = cv2.dilate(surface.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    return surface, near


def _pair(*, gap: bool, twin: bool = False, gain: float = 1.0, offset: float = 0.0, seed: int = 0):
    """Photo k-1 and photo k: the new layer covers SURFACE with new beads (or the twin of the old ones,
    one layer higher), except GAP when ``gap``; photo k under another exposure when asked."""
    rng = np.random.default_rng(seed + 100)
    before = _scene(seed)
    after = before.copy()
    new = _shift(before, SHIFT) if twin else _scene(seed + 1)  # twin: new(p) = before(p + SHIFT)
    after[SURFACE] = new[SURFACE]
    if gap:
        after[GAP] = before[GAP]
    return highpass(_photo(before, rng)), highpass(_photo(after, rng, gain, offset))


def _gap_blocks(bp: int) -> np.ndarray:
    out = np.zeros((H // bp, W // bp), bool)
    out[GAP[0].start // bp:GAP[0].stop // bp, GAP[1].start // bp:GAP[1].stop // bp] = True
    return out


@pytest.mark.parametrize("twin", [False, True])
def test_a_gap_in_the_new_layer_is_unchanged_and_the_printed_rest_is_not(twin):
    st = LayerChangeSettings(enabled=True)
    b, a = _pair(gap=True, twin=twin)
    surface, near = _masks()
    ch = block_change(a, b, surface, near, SHIFT, st)
    assert ch is not None and ch.judged.sum() > 100
    gap = _gap_blocks(st.block_px)
    assert ch.unchanged[gap].mean() >= 0.8, "the missed area looks as in the previous photo"
    assert not ch.unchanged[~gap].any(), "new beads (or a twin one layer higher) changed the rest"
    assert 0 < ch.noise < 20


def test_a_perimeter_laid_on_its_twin_looks_alike_at_the_same_pixels_and_more_so_shifted():
    # what the parallax test is for: against the same pixels alone, a twin bead one layer up looks alike
    b, a = _pair(gap=False, twin=True)
    surface, near = _masks()
    ch = block_change(a, b, surface, near, SHIFT, LayerChangeSettings(enabled=True))
    assert ch is not None and not ch.unchanged.any()
    assert np.median(ch.ncc[ch.judged]) > 0.3
    assert np.all(ch.ncc_twin[ch.judged] > ch.ncc[ch.judged])


@pytest.mark.parametrize(("gain", "offset"), [(1.0, 0.0), (1.35, -20.0), (0.7, 15.0)])
def test_a_clean_layer_under_new_exposure_and_noise_has_no_unchanged_block(gain, offset):
    b, a = _pair(gap=False, gain=gain, offset=offset, seed=3)
    surface, near = _masks()
    ch = block_change(a, b, surface, near, SHIFT, LayerChangeSettings(enabled=True))
    assert ch is not None and ch.judged.sum() > 100
    assert not ch.unchanged.any()


def test_a_black_previous_photo_gives_no_verdict():
    _, a = _pair(gap=True)
    surface, near = _masks()
    black = highpass(np.zeros((H, W), np.uint8))
    assert block_change(a, black, surface, near, SHIFT, LayerChangeSettings(enabled=True)) is None


def test_flat_texture_is_not_judged():
    # a dark, textureless filament: no block stands above the noise, so none is unchanged (and none failed)
    rng = np.random.default_rng(1)
    before, after = _scene(0), _scene(0)
    flat = np.full((H, W), 20.0, np.float32)
    before[SURFACE] = flat[SURFACE]
    after[SURFACE[0].start - 2:SURFACE[0].stop - 2, SURFACE[1]] = 20.0  # one layer higher: seen ~2 px higher
    b, a = highpass(_photo(before, rng)), highpass(_photo(after, rng))
    surface, near = _masks()
    st = LayerChangeSettings(enabled=True)
    ch = block_change(a, b, surface, near, SHIFT, st)
    assert ch is not None and not ch.unchanged.any()
    bp = st.block_px  # inside, away from the textured border that the high pass spreads over its edge
    inner = ch.judged[SURFACE[0].start // bp + 2:SURFACE[0].stop // bp - 2, SURFACE[1].start // bp + 2:SURFACE[1].stop // bp - 2]
    assert inner.size > 50 and not inner.any()


def test_settings_refuse_out_of_range_values():
    with pytest.raises(ValidationError):
        LayerChangeSettings(block_px=1)
    with pytest.raises(ValidationError):
        LayerChangeSettings(min_ncc=1.5)


def test_parallax_of_a_plane_map_is_the_shift_of_the_rays():
    # rays whose top-view point moves by (0, 2) px per mm of height, 1 top px per image px: 0.4 mm -> 0.8 px
    yy, xx = np.mgrid[0:40, 0:50].astype(np.float32)
    A = np.stack([xx, yy])
    B = np.stack([np.zeros_like(xx), np.full_like(yy, 2.0)])
    dx, dy = parallax_px((A, B), 3.0, 0.4)
    assert dx == pytest.approx(0.0, abs=1e-6) and dy == pytest.approx(0.8, abs=1e-6)


def test_blocks_are_carried_to_the_top_view_and_counted_once_into_a_percent():
    tv = TopView(10.0, 20.0, 20.0, (0.0, 0.0))  # 200 x 200 px
    blocks = np.zeros((10, 10), bool)
    blocks[2:4, 5] = True  # working px rows 16-31, cols 40-47 (8 px blocks): photo px y in [15.5, 31.5)
    yy, xx = np.mgrid[0:200, 0:200].astype(np.float32)
    source = (xx / 2.0, yy / 2.0)  # photo px seen at each top px; the working image is the photo
    where = np.ones((200, 200), bool)
    top = blocks_on_top(blocks, 8, (0, 0), (1.0, 1.0), source, where)
    vv, uu = np.nonzero(top)
    assert (vv.min(), vv.max(), uu.min(), uu.max()) == (31, 62, 79, 94)
    res = LayerResult(layer=3, z=0.6, threshold=0.5, printed_area_mm2=100.0, anomalous_area_mm2=0.0,
                      heatmap=np.ones((20, 20), np.float32), mask=np.ones((20, 20), bool),
                      grid=BlockGrid(cell_px=10, block_cells=2))
    region = Region(area_mm2=float(top.sum()) / 100.0, bbox_mm=(0, 0, 1, 1), centroid_mm=(0, 0), n_blocks=1,
                    mean_similarity=0.0, kind="infill_defect")
    added = add_unchanged(res, top, [region], tv)
    assert added == pytest.approx(top.sum() / 100.0)
    assert res.anomaly_ratio == pytest.approx(added / 100.0) and res.regions == [region]
    res.heatmap[3:6, 7:9] = 0.0  # HOG blocks already anomalous there: that area is not counted twice
    again = LayerResult(layer=3, z=0.6, threshold=0.5, printed_area_mm2=100.0, heatmap=res.heatmap,
                        mask=res.mask, grid=res.grid)
    assert add_unchanged(again, top, [region], tv) < added


def test_only_groups_unchanged_in_the_previous_pair_too_fail():
    now = np.zeros((10, 12), bool)
    now[2:4, 2:5] = True  # the gap, unchanged again
    now[7, 9] = True  # a chance likeness, new here
    before = np.zeros_like(now)
    before[3, 5] = True  # touches the gap's group (8-connected, one block off)
    before[0, 0] = True
    kept = persistent_groups(now, before, 1)
    assert kept[2:4, 2:5].all() and not kept[7, 9] and kept.sum() == 6
    assert not persistent_groups(now, None, 1).any(), "the first judged pair of a print reports nothing"
    assert not persistent_groups(now, before, 7).any(), "a group smaller than min_blocks is dropped"
