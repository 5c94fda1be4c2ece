"""What the previous photo saw past the part (analysis/seen_past.py): the band the rising far wall hides.

Geometry of the synthetic views: the working image is the top view at Z = 0, and a ray's point
on the plane Z = z moves by (0, 2) top-view px per mm of height, so a lower plane is met at a
smaller row: the footprint's low-row edge is the far silhouette (beyond it the camera sees past
the part), its high-row edge faces the camera (beyond it the camera sees the part's own face).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.analysis.block_masks import fill_holes
from layerwatch.analysis.scene_change import predicted_change, top_coords
from layerwatch.analysis.seen_past import (
    BLIND_SHARE,
    CLOSE_MM,
    EDGE_PX,
    outline_of,
    past_share,
    seen_past,
)
from layerwatch.geometry.topview import TopView

TV = TopView(10.0, 20.0, 20.0, (0.0, 0.0))  # 200 x 200 px, 10 px/mm
YY, XX = np.mgrid[0:200, 0:200].astype(np.float32)
MAPS = (np.stack([XX, YY]), np.stack([np.zeros_like(XX), np.full_like(YY, 2.0)]))
Z, Z_BEFORE = 3.6, 2.0  # 3.2 px of rise between the photos
NOISE = 0.25  # the texture's faint noise (sigma 0.5), as the pair's calibration would find it


def _footprint() -> np.ndarray:
    fp = np.zeros(TV.shape, bool)
    fp[60:140, 40:160] = True
    return fp


def _surface(fp: np.ndarray) -> np.ndarray:
    return predicted_change(fp, np.array([Z]), MAPS, TV, 0.0)


def _texture(rows: slice, seed: int = 0) -> np.ndarray:
    """Previous photo's high-passed texture: faint noise everywhere, strong lines in ``rows``."""
    rng = np.random.default_rng(seed)
    tex = rng.normal(0.0, 0.5, TV.shape).astype(np.float32)
    tex[rows, 40:160] += np.where(np.arange(rows.stop - rows.start)[:, None] % 4 < 2, 20.0, -20.0)
    return tex


def test_a_skirt_behind_the_far_wall_blinds_the_far_edge_only():
    fp = _footprint()
    surface = _surface(fp)
    far = int(np.flatnonzero(surface.any(axis=1))[0])  # the far silhouette's row (plane Z)
    # the skirt line lay just past the far wall in the previous photo, where the new layer now stands
    blind = seen_past(surface, fp, Z, Z_BEFORE, MAPS, TV, _texture(slice(far - 4, far + 3)), NOISE)
    rows = np.flatnonzero(blind.any(axis=1))
    assert rows.size and rows[0] >= far and rows[-1] <= far + 12  # the far edge, within 4 window sigmas
    assert not blind[far + 20:].any()  # the middle and the camera-facing edge are judged
    assert not (blind & ~surface).any()


def test_the_share_seen_past_is_what_the_blind_test_thresholds():
    fp = _footprint()
    surface = _surface(fp)
    far = int(np.flatnonzero(surface.any(axis=1))[0])
    tex = _texture(slice(far - 4, far + 3))
    share = past_share(surface, fp, Z, Z_BEFORE, MAPS, TV, tex, NOISE)
    assert np.array_equal(share >= BLIND_SHARE, seen_past(surface, fp, Z, Z_BEFORE, MAPS, TV, tex, NOISE))
    valid = share >= 0
    assert valid.any() and not (valid & ~surface).any() and share.max() <= 1.0
    # a lower share reaches further into the top than the blind band: what the wall runs keep out
    assert (share >= 0.05).sum() > (share >= BLIND_SHARE).sum()
    assert (past_share(surface, fp, Z, Z, MAPS, TV, tex, NOISE) == -1).all()  # no rise: nothing seen past


def test_a_plain_bed_behind_the_far_wall_blinds_nothing():
    fp = _footprint()
    surface = _surface(fp)
    tex = _texture(slice(100, 120))  # texture on the part's own top (infill lines), nothing behind it
    assert not seen_past(surface, fp, Z, Z_BEFORE, MAPS, TV, tex, NOISE).any()


def test_texture_in_front_of_the_part_is_its_own_face_not_past_it():
    fp = _footprint()
    surface = _surface(fp)
    near = int(np.flatnonzero(surface.any(axis=1))[-1])  # the camera-facing silhouette
    tex = _texture(slice(near - 2, near + 6))  # the face below the near edge: layer lines
    assert not seen_past(surface, fp, Z, Z_BEFORE, MAPS, TV, tex, NOISE).any()


def test_no_rise_no_band():
    fp = _footprint()
    surface = _surface(fp)
    tex = _texture(slice(50, 70))
    assert not seen_past(surface, fp, Z, Z, MAPS, TV, tex, NOISE).any()
    assert not seen_past(np.zeros_like(surface), fp, Z, Z_BEFORE, MAPS, TV, tex, NOISE).any()
    assert 0 < BLIND_SHARE < 1


def test_the_outline_fills_infill_cells_and_holes_but_not_a_notch_open_to_the_outside():
    fp = np.zeros(TV.shape, bool)
    fp[40:160, 40:42] = fp[40:160, 158:160] = fp[40:42, 40:160] = fp[158:160, 40:160] = True  # the walls
    fp[40:160, 40:160] |= (np.add.outer(np.arange(200), np.arange(200))[40:160, 40:160] % 60) < 6  # infill, 6 mm
    fp[80:120, 80:120] = False
    fp[78:80, 78:122] = fp[120:122, 78:122] = fp[78:122, 78:80] = fp[78:122, 120:122] = True  # a hole's wall
    fp[85:115, 150:160] = False  # a 3 mm notch through the right wall
    out = outline_of(fp, TV)
    assert out[60:70, 60:70].all()  # between infill lines: inside the part
    assert out[90:110, 90:110].all()  # a hole: the part's own inner faces, not past the part
    assert not out[92:108, 152:200].any()  # the notch and the bed beyond it: outside
    assert not out[:30].any() and not out[170:].any()


def test_the_part_s_own_edge_texture_beside_a_side_wall_is_not_past_it():
    fp = _footprint()
    surface = _surface(fp)
    tex = np.random.default_rng(1).normal(0.0, 0.5, TV.shape).astype(np.float32)
    tex[56:130, 38:40] += 20.0  # the high pass of the side wall's bright edge rings onto the bed beside it
    tex[56:130, 40:42] -= 20.0
    assert not seen_past(surface, fp, Z, Z_BEFORE, MAPS, TV, tex, NOISE).any()


def _outline_whole(fp: np.ndarray) -> np.ndarray:
    """The outline computed on the whole view (zero padding by more than the closing reaches)."""
    k = int(round(CLOSE_MM * TV.px_per_mm)) | 1
    pad = k + 1
    big = cv2.copyMakeBorder(fp.astype(np.uint8), pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    closed = cv2.morphologyEx(big, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    return fill_holes(closed)[pad:-pad, pad:-pad]


def _past_share_whole(surface, fp, tex, noise=NOISE, sig=3.0):
    """The share computed on the whole working image: band, blurs and all."""
    out = np.full(surface.shape, -1.0, np.float32)
    outline = _outline_whole(fp).astype(np.uint8)

    def outside(zp):
        seen = cv2.remap(outline, *top_coords(MAPS, zp), cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0)
        return cv2.dilate(seen, np.ones((2 * EDGE_PX + 1,) * 2, np.uint8)) == 0

    band = outside(Z_BEFORE) & outside(0.0)
    e = tex**2
    hidden = cv2.GaussianBlur(np.where(band, e, 0).astype(np.float32), (0, 0), sig)
    total = cv2.GaussianBlur(e, (0, 0), sig)
    valid = surface & (hidden >= 2.0 * noise)
    out[valid] = hidden[valid] / (total[valid] + 1e-6)
    return out


@pytest.mark.parametrize("seed", range(8))
def test_the_outline_and_the_share_on_the_surface_s_box_are_the_whole_image_s_bit_for_bit(seed):
    """Placed anywhere, at the view's borders too (the right border: whole rows), infill cells and all."""
    rng = np.random.default_rng(seed)
    fp = np.zeros(TV.shape, bool)
    for _ in range(int(rng.integers(1, 4))):
        v0, u0 = (int(x) for x in rng.integers(-20, 190, 2))
        v1, u1 = v0 + int(rng.integers(8, 90)), u0 + int(rng.integers(8, 90))
        fp[max(v0, 0):v1, max(u0, 0):u1] = True
    fp &= (np.add.outer(np.arange(200), np.arange(200)) % int(rng.integers(9, 40))) > 2  # infill cells
    assert np.array_equal(outline_of(fp, TV), _outline_whole(fp))
    tex = rng.normal(0.0, 0.5, TV.shape).astype(np.float32)
    tex[rng.random(TV.shape) < 0.05] += 20.0  # lines and specks all over: past the part too
    surface = _surface(fp)
    share = past_share(surface, fp, Z, Z_BEFORE, MAPS, TV, tex, NOISE)
    assert (share >= 0).any()
    assert np.array_equal(share, _past_share_whole(surface, fp, tex))


@pytest.mark.slow
def test_simplify3d_far_wall_over_its_skirt_is_not_an_unchanged_wall():
    """The real file: Simplify3D 4.1.2's skirt lies 2 mm outside the first layer; the disc's far wall
    hides it while it rises (layers 7 -> 13: 14-34 mm^2 of "thin-wall gap" before this module)."""
    from pathlib import Path

    from layerwatch.gcode import read_toolpath
    from layerwatch.geometry.settings import TopViewSettings
    from layerwatch.pipeline.config import resolve_config
    from layerwatch.pipeline.step import LayerPipeline
    from layerwatch.simulate import PrintSimulator
    from layerwatch.simulate.scene import default_camera

    path = Path(__file__).resolve().parents[3] / "shared" / "data" / "gcode" / "simplify3d-4.1.2_zlift.gcode"
    if not path.is_file():
        path = Path("/work/shared/data/gcode/simplify3d-4.1.2_zlift.gcode")
    if not path.is_file():
        pytest.skip("the shared real-slicer corpus is not here")
    tp = read_toolpath(path)
    x0, y0, x1, y1 = tp.bounds
    side = max(x1 - x0, y1 - y0) * 1.5
    square = {"center_mm": ((x0 + x1) / 2, (y0 + y1) / 2), "width_mm": side, "height_mm": side}
    tv = TopViewSettings(**square).topview()
    cam = default_camera(tv, image_size=(1280, 720))
    cfg = resolve_config(recommended=True, flags={"topview": square}).config.for_camera(cam)
    sim = PrintSimulator(tp, cam, cfg.topview.topview(), seed=31)
    pipe = LayerPipeline(tp, cam, cfg, bed_photo=sim.bed_photo())
    pipe.process(sim.frame(7).photo, 7)
    res = pipe.process(sim.frame(13).photo, 13)
    lc = res.layer_change
    assert lc is not None and lc.judged and lc.px_judged > 5000
    assert lc.unchanged_mm2 < 5.0  # the policy's minimum area: no alarm from this channel
