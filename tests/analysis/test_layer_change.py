"""The "changed as predicted" channel (issue 18): unchanged footprint pixels on synthetic photo pairs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from layerwatch.analysis.extrusion import highpass
from layerwatch.analysis.layer_change import (
    CLIP_LEVEL,
    LayerChangeSettings,
    add_unchanged,
    blocks_on_top,
    clipped_box,
    drop_edge_slivers,
    parallax_px,
    window_change,
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


def _gap_px(reach: int) -> np.ndarray:
    """The gap's pixels farther than ``reach`` from its border (their windows see the gap only)."""
    out = np.zeros((H, W), bool)
    out[GAP[0].start + reach:GAP[0].stop - reach, GAP[1].start + reach:GAP[1].stop - reach] = True
    return out


def _inner(margin: int) -> np.ndarray:
    """The footprint's pixels at least ``margin`` px inside it (its outer rows mix the cut of the synthetic bead)."""
    out = np.zeros((H, W), bool)
    out[SURFACE[0].start + margin:SURFACE[0].stop - margin, SURFACE[1].start + margin:SURFACE[1].stop - margin] = True
    return out


def _near_gap(reach: int) -> np.ndarray:
    out = np.zeros((H, W), bool)
    out[GAP[0].start - reach:GAP[0].stop + reach, GAP[1].start - reach:GAP[1].stop + reach] = True
    return out


@pytest.mark.parametrize("twin", [False, True])
def test_a_gap_in_the_new_layer_is_unchanged_and_the_printed_rest_is_not(twin):
    st = LayerChangeSettings(enabled=True)
    b, a = _pair(gap=True, twin=twin)
    surface, near = _masks()
    ch = window_change(a, b, surface, near, SHIFT, st)
    assert ch is not None and ch.judged.sum() > 5000
    reach = int(2 * st.window_px)
    assert ch.unchanged[_gap_px(reach)].mean() >= 0.9, "the missed area looks as in the previous photo"
    rest = ~_near_gap(reach)
    assert not ch.unchanged[rest & _inner(1)].any(), "new beads (or a twin one layer higher) changed the rest"
    assert ch.unchanged[rest].sum() < 10, "only stray pixels on the footprint's outer row (far below min_area_mm2)"
    assert 0 < ch.noise < 20


def test_a_perimeter_laid_on_its_twin_looks_alike_at_the_same_pixels_and_more_so_shifted():
    # what the parallax test is for: against the same pixels alone, a twin bead one layer up looks alike
    b, a = _pair(gap=False, twin=True)
    surface, near = _masks()
    ch = window_change(a, b, surface, near, SHIFT, LayerChangeSettings(enabled=True))
    assert ch is not None and not ch.unchanged[_inner(1)].any() and ch.unchanged.sum() < 10
    assert np.median(ch.same[ch.judged]) > 0.3
    assert np.mean((ch.twin > ch.same)[ch.judged & _inner(1)]) > 0.99


@pytest.mark.parametrize(("gain", "offset"), [(1.0, 0.0), (1.35, -20.0), (0.7, 15.0)])
def test_a_clean_layer_under_new_exposure_and_noise_has_no_unchanged_pixel(gain, offset):
    b, a = _pair(gap=False, gain=gain, offset=offset, seed=3)
    surface, near = _masks()
    ch = window_change(a, b, surface, near, SHIFT, LayerChangeSettings(enabled=True))
    assert ch is not None and ch.judged.sum() > 5000
    # only stray pixels on the footprint's outer rows, whose windows are mostly the unchanged texture beside it
    assert not ch.unchanged[_inner(1)].any() and ch.unchanged.sum() < 10


@pytest.mark.parametrize(("gain", "offset"), [(1.35, -20.0), (0.7, 15.0)])
def test_a_gap_under_new_exposure_is_still_found(gain, offset):
    st = LayerChangeSettings(enabled=True)
    b, a = _pair(gap=True, gain=gain, offset=offset, seed=5)
    surface, near = _masks()
    ch = window_change(a, b, surface, near, SHIFT, st)
    assert ch is not None and ch.unchanged[_gap_px(int(2 * st.window_px))].mean() >= 0.9


def test_a_bead_along_the_parallax_is_not_judged():
    # texture that does not vary along the parallax direction looks the same shifted: no verdict, not a gap
    rng = np.random.default_rng(2)
    cols = cv2.GaussianBlur(rng.normal(0, 1, (1, W)).astype(np.float32), (0, 0), 1.2)
    stripes = np.clip(128 + 40 * np.repeat(cols / cols.std(), H, axis=0), 0, 255).astype(np.float32)
    before = _scene(0)
    before[SURFACE] = stripes[SURFACE]
    after = before.copy()  # nothing printed: the same stripes
    b, a = highpass(_photo(before, rng)), highpass(_photo(after, rng))
    surface, near = _masks()
    ch = window_change(a, b, surface, near, SHIFT, LayerChangeSettings(enabled=True))
    inner = np.zeros((H, W), bool)
    inner[SURFACE[0].start + 10:SURFACE[0].stop - 10, SURFACE[1].start + 10:SURFACE[1].stop - 10] = True
    assert ch is not None and not ch.judged[inner].any() and not ch.unchanged[inner].any()


def test_a_black_previous_photo_gives_no_verdict():
    _, a = _pair(gap=True)
    surface, near = _masks()
    black = highpass(np.zeros((H, W), np.uint8))
    assert window_change(a, black, surface, near, SHIFT, LayerChangeSettings(enabled=True)) is None


def test_flat_texture_is_not_judged():
    # a dark, textureless filament: no window stands above the noise, so none is unchanged (and none failed)
    rng = np.random.default_rng(1)
    before, after = _scene(0), _scene(0)
    flat = np.full((H, W), 20.0, np.float32)
    before[SURFACE] = flat[SURFACE]
    after[SURFACE[0].start - 2:SURFACE[0].stop - 2, SURFACE[1]] = 20.0  # one layer higher: seen ~2 px higher
    b, a = highpass(_photo(before, rng)), highpass(_photo(after, rng))
    surface, near = _masks()
    st = LayerChangeSettings(enabled=True)
    ch = window_change(a, b, surface, near, SHIFT, st)
    # stray pixels where the high pass spreads the footprint's static side edge into it: specks of a few
    # pixels (a 0.5 mm^2 region, min_area_mm2, is about 18 px at the simulator's 0.14 x 0.2 mm per px)
    assert ch is not None and not ch.unchanged[_inner(4)].any()
    n, _, stats, _ = cv2.connectedComponentsWithStats(ch.unchanged.astype(np.uint8), connectivity=8)
    assert stats[1:, cv2.CC_STAT_AREA].max(initial=0) < 16
    m = int(4 * st.window_px)  # inside, away from the textured border that the high pass spreads over its edge
    inner = ch.judged[SURFACE[0].start + m:SURFACE[0].stop - m, SURFACE[1].start + m:SURFACE[1].stop - m]
    assert inner.size > 5000 and not inner.any()


def test_settings_refuse_out_of_range_values():
    with pytest.raises(ValidationError):
        LayerChangeSettings(block_px=1)
    with pytest.raises(ValidationError):
        LayerChangeSettings(window_px=0)
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


def test_an_unchanged_band_along_either_silhouette_edge_is_dropped_a_gap_through_a_wall_is_kept():
    # parallax (0, 1.5): a lower point is seen lower in the image, so the edge facing the camera is the bottom one
    surface = np.zeros((H, W), bool)
    surface[60:200, 40:150] = True  # a wide top surface
    surface[194:200, 180:300] = True  # a thin wall, 6 px
    surface[20:29, 180:300] = True  # a 1.8 mm wall, 9 px (the window part's box)
    unchanged = np.zeros((H, W), bool)
    unchanged[193:200, 60:120] = True  # the wide surface's front edge band
    unchanged[60:65, 60:120] = True  # its back edge band (the far silhouette)
    unchanged[194:200, 200:260] = True  # the thin wall's gap: its whole cross-section
    unchanged[100:120, 60:80] = True  # a patch inside the wide surface
    unchanged[24:29, 190:240] = True  # the 9 px wall's front silhouette stayed in place, its back half changed
    unchanged[20:29, 250:290] = True  # a gap through the 9 px wall
    kept = drop_edge_slivers(unchanged, surface, SHIFT, 6, 3)
    assert not kept[193:200, 60:120].any() and not kept[60:65, 60:120].any(), "silhouette bands of a surface go"
    assert not kept[24:29, 190:240].any(), "a wall's front silhouette alone goes"
    assert kept[194:200, 200:260].all() and kept[20:29, 250:290].all(), "a gap through a wall stays"
    assert kept[100:120, 60:80].all(), "an inner patch stays"
    flipped = drop_edge_slivers(unchanged, surface, (0.0, -1.5), 6, 3)  # camera on the other side: the same edges
    assert np.array_equal(flipped, kept)
    assert drop_edge_slivers(unchanged, surface, (0.0, 0.0), 6, 3).sum() == unchanged.sum()


def test_a_glare_spot_that_stays_in_place_is_not_taken_for_an_unchanged_surface():
    # a fixed lamp's highlight on a glossy top surface: clipped in both photos at the same place while the
    # layer under it was printed; its border is static texture, which without the clipped mask looks unchanged
    rng = np.random.default_rng(100)
    before = _scene(0)
    after = before.copy()
    after[SURFACE] = _scene(1)[SURFACE]
    yy, xx = np.mgrid[0:H, 0:W]
    blob = ((yy - 130) ** 2 / 400 + (xx - 170) ** 2 / 900) < 1
    before[blob] = after[blob] = 255.0
    p0, p1 = _photo(before, rng), _photo(after, rng)
    b, a = highpass(p0), highpass(p1)
    surface, near = _masks()
    st = LayerChangeSettings(enabled=True)
    whole = (slice(0, H), slice(0, W))
    clipped = clipped_box(p0, (W, H), whole) | clipped_box(p1, (W, H), whole)
    assert clipped[130, 170] and not clipped[200, 60] and clipped.shape == (H, W)
    blind = window_change(a, b, surface, near, SHIFT, st)
    assert blind is not None and blind.unchanged.sum() > 100, "the glare's border looks unchanged"
    ch = window_change(a, b, surface, near, SHIFT, st, clipped)
    assert ch is not None and not ch.unchanged[_inner(1)].any() and ch.judged.sum() > 4000


def test_clipped_pixels_are_found_in_a_larger_colour_frame():
    photo = np.full((480, 640, 3), 120, np.uint8)
    photo[100:110, 200:220] = 255  # white glare: every channel clipped
    photo[300:310, 200:220, 2] = 255  # a saturated red filament: one channel clipped, the others carry texture
    out = clipped_box(photo, (320, 240), (slice(40, 160), slice(90, 130)))  # working px = 2 x 2 photo px
    assert out.shape == (120, 40)
    assert out[50 - 40, 100 - 90] and out.sum() == 5 * 10, "the glare, at half the photo's scale"
    assert not out[150 - 40].any(), "a clipped colour channel is not glare"


def test_moved_pixels_are_the_outlines_of_moved_regions_or_their_boxes_and_apart_from_leaves_them_out():
    from layerwatch.analysis.layer_change import apart_from, moved_pixels
    from layerwatch.analysis.region_outline import outline_mask, outline_mm
    from layerwatch.analysis.result import Region
    from layerwatch.geometry.topview import TopView

    tv = TopView(px_per_mm=5.0, width_mm=40.0, height_mm=40.0, center_mm=(100.0, 100.0))
    band = np.zeros(tv.shape, bool)
    band[40:60, 20:30] = True
    shaped = Region(200.0, (84.0, 88.0, 86.0, 92.0), (85.0, 90.0), 4, 0.2, kind="layer_shift",
                    outline_mm=outline_mm(band, tv))
    boxed = Region(4.0, (110.0, 110.0, 112.0, 112.0), (111.0, 111.0), 1, 0.2, kind="layer_shift")
    m = moved_pixels([shaped, boxed], tv)
    assert m[outline_mask(shaped.outline_mm, tv)].all()
    (u0, v0), (u1, v1) = np.round(tv.to_px(np.array([[110.0, 112.0], [112.0, 110.0]]))).astype(int)
    assert m[v0: v1 + 1, u0: u1 + 1].all()
    assert int(m.sum()) == int(outline_mask(shaped.outline_mm, tv).sum()) + (v1 - v0 + 1) * (u1 - u0 + 1)
    everywhere = np.ones(tv.shape, bool)
    kept = apart_from(everywhere, m, 1.0, tv)
    assert not (kept & m).any() and kept[50, 20 - 6] and not kept[50, 20 - 4]  # 1 mm = 5 px beside the band
    assert np.array_equal(apart_from(everywhere, np.zeros_like(m), 1.0, tv), everywhere)


@pytest.mark.parametrize(("photo_size", "size"), [((1920, 1080), (1280, 720)), ((1920, 1080), (640, 360)),
                                                   ((1000, 750), (600, 450)), ((1280, 720), (1280, 720))])
def test_clipped_box_resizes_only_the_rows_with_glare_as_the_whole_box_would(photo_size, size):
    """The working rows without a clipped source pixel are not resized (scales p / 2^k; others: the whole box)."""
    rng = np.random.default_rng(sum(photo_size) + size[0])
    (pw, ph), (W, H) = photo_size, size
    for _ in range(12):
        photo = np.full((ph, pw, 3), 120, np.uint8)
        for _ in range(int(rng.integers(1, 4))):  # glare spots, some a single pixel
            y, x = int(rng.integers(0, ph)), int(rng.integers(0, pw))
            photo[y:y + int(rng.integers(1, 30)), x:x + int(rng.integers(1, 30))] = 255
        r0, c0 = int(rng.integers(0, H // 2)), int(rng.integers(0, W // 2))
        box = (slice(r0, r0 + int(rng.integers(20, H // 2))), slice(c0, c0 + int(rng.integers(20, W // 2))))
        y0, y1 = int(np.floor(box[0].start * ph / H)), int(np.ceil(box[0].stop * ph / H))
        x0, x1 = int(np.floor(box[1].start * pw / W)), int(np.ceil(box[1].stop * pw / W))
        hot = cv2.inRange(np.ascontiguousarray(photo[y0:y1, x0:x1]), (CLIP_LEVEL,) * 3, (255,) * 3)
        want = cv2.resize(hot, (box[1].stop - box[1].start, box[0].stop - box[0].start),
                          interpolation=cv2.INTER_AREA) > 0
        assert np.array_equal(clipped_box(photo, size, box), want)
