"""The part's cast shadow beside the print: light, not material (analysis/cast_shadow.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.analysis.cast_shadow import MIN_GAIN, explained_by_shade, roof_area, shadow_zone
from layerwatch.analysis.scene_change import change_blocks
from layerwatch.analysis.settings import SceneSettings

H, W, B = 160, 240, 8


def _surface(rgb=(0.9, 0.55, 0.2), level=170.0, seed=0) -> np.ndarray:
    """A printed floor: a fine bead texture around ``level``, tinted ``rgb``, float32 (H, W, 3)."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.normal(0, 12, (H, W)).astype(np.float32), (0, 0), 1.0)
    beads = 6.0 * np.sin(np.arange(W, dtype=np.float32) * 1.3)[None, :]
    grey = level + tex + beads
    return np.clip(grey[..., None] * np.array(rgb, np.float32) / max(rgb), 0, 255).astype(np.float32)


def _noisy(img: np.ndarray, seed: int, sigma: float = 1.5) -> np.ndarray:
    return np.clip(img + np.random.default_rng(seed).normal(0, sigma, img.shape), 0, 255).astype(np.float32)


def _judge(photo: np.ndarray, expected: np.ndarray, zone: np.ndarray, whole: np.ndarray | None = None):
    scored = np.ones((H, W), bool)
    ratio = np.ones((H, W, 3), np.float32)
    change = change_blocks(photo, expected, scored, ratio, SceneSettings(enabled=True))
    shaded = explained_by_shade(change, photo, np.minimum(expected * ratio, 255.0), scored, zone, whole=whole)
    return change, shaded


def _shadow(img: np.ndarray, gain: float, x0: int = 100, slope: float = 0.3) -> np.ndarray:
    """``img`` darkened by ``gain`` right of a sharp slanted edge (a wall's cast shadow), with no blur."""
    yy, xx = np.mgrid[0:H, 0:W]
    inside = xx > x0 + slope * yy
    return np.where(inside[..., None], img * gain, img).astype(np.float32)


def test_the_zone_reaches_the_given_distance_from_the_body_and_nothing_without_a_body():
    body = np.zeros((H, W), bool)
    body[70:90, 110:130] = True
    zone = shadow_zone(body, 20.0)
    assert zone[body].all()
    assert zone[80, 110 - 19] and not zone[80, 110 - 22]
    assert zone[70 - 19, 120] and not zone[70 - 22, 120]
    assert not shadow_zone(np.zeros((H, W), bool), 20.0).any()
    assert not shadow_zone(body, 0.0).any()


@pytest.mark.parametrize("gain", [0.6, 0.8, 1.25])
def test_a_grey_shadow_whose_sharp_edge_advanced_changes_blocks_that_the_shade_explains(gain):
    """The shadow was in ``E`` already; its edge moved 4 px (a taller wall, or the lamp's sway)."""
    E = _shadow(_surface(), gain, x0=104)
    photo = _noisy(_shadow(_surface(), gain, x0=100), 1)
    zone = np.ones((H, W), bool)
    change, shaded = _judge(photo, _noisy(E, 2), zone)
    assert change.changed.sum() >= 5  # the scene channel alone reports the shadow (its edge at least)
    assert (shaded <= change.changed).all()
    assert shaded.sum() >= 0.9 * change.changed.sum()


def test_a_fresh_shadow_over_whole_blocks_is_not_explained_inside_them():
    """A shadow that covers whole blocks at once (an overhang's, printed in one layer) looks like a clump that
    landed there: its inner blocks stay changes (the module's note: the price of catching such clumps)."""
    E = _surface()
    change, shaded = _judge(_noisy(_shadow(E, 0.6), 1), _noisy(E, 2), np.ones((H, W), bool))
    inner = change.changed.copy()
    inner[:, : (100 + int(0.3 * H)) // B + 2] = False  # right of the edge's last block
    assert inner.sum() >= 10 and not (shaded & inner).any()


def test_under_a_roof_a_fresh_shadow_over_whole_blocks_is_shade():
    """The same fresh shadow under a roof of the part (a bridge's deck closing over the bed): the shade does
    cover whole blocks at once there, so they may move entirely (grey, in range, texture kept, one way)."""
    E = _surface()
    under = np.zeros((H, W), bool)
    under[:, 100:] = True  # the roof's zone: right of the shadow's edge
    change, shaded = _judge(_noisy(_shadow(E, 0.6), 1), _noisy(E, 2), np.ones((H, W), bool), whole=under)
    inner = change.changed.copy()
    inner[:, : (100 + int(0.3 * H)) // B + 2] = False
    assert inner.sum() >= 10 and (shaded & inner).sum() >= 0.9 * inner.sum()


def _strands(E: np.ndarray) -> np.ndarray:
    """A few loops of filament of the floor's own colour over ``E``, lit on top and dark at their edges."""
    photo = E.copy()
    yy, xx = np.mgrid[0:H, 0:W]
    d = yy - (40 + 0.4 * xx)
    for off in (0.0, 5.0, 10.0, 15.0):
        dd = np.abs(d - off)
        photo = np.where((dd < 2.0)[..., None], photo * np.where(dd < 1.0, 1.3, 0.5)[..., None], photo)
    return np.clip(photo, 0, 255).astype(np.float32)


def _screw(E: np.ndarray) -> np.ndarray:
    photo = E.copy()
    photo[60:100, 80:140] = np.clip(photo[60:100, 80:140] * 5.0, 0, 255)
    return photo


def _lump(E: np.ndarray) -> np.ndarray:
    photo = E.copy()
    photo[60:100, 80:140] *= 0.5 * MIN_GAIN
    return photo


@pytest.mark.parametrize(("floor", "put", "most"), [
    ({}, _strands, 0.2),  # an orange clump on the orange floor: its texture stays
    ({"rgb": (1.0, 0.95, 0.9), "level": 30.0}, _screw, 0.0),  # a bright screw on a dark sheet: a gain of 5
    ({"rgb": (1.0, 0.95, 0.9), "level": 120.0}, _lump, 0.0),  # a black lump: deeper than a shadow
])
def test_under_a_roof_material_is_still_not_shade(floor, put, most):
    """The roof lifts only the whole-block cap: what the other tests refuse stays a change under a bridge too."""
    E = _surface(**floor)
    change, shaded = _judge(_noisy(put(E), 1), _noisy(E, 2), np.ones((H, W), bool), whole=np.ones((H, W), bool))
    assert change.changed.sum() >= 5
    assert shaded.sum() <= most * change.changed.sum()


def test_a_roof_is_material_printed_over_air_wider_than_a_bead():
    px = 8.0  # px/mm
    below = np.zeros((200, 300), bool)
    below[40:160, 20:60] = below[40:160, 140:180] = True  # two pillars
    deck = below.copy()
    deck[40:160, 60:140] = True  # a bridge's deck between them
    roof = roof_area(deck, below, 1.5, px)
    assert roof[100, 74:126].all() and not roof[100, :70].any() and not roof[100, 130:].any()  # 1.5 mm off each
    assert roof.sum() >= 0.8 * (120 * 80 - 2 * 12 * 120)  # all but the margin along each pillar
    lean = np.zeros_like(below)
    lean[38:162, 18:62] = True  # the pillar one bead (0.25 mm) wider all round: a wall leaning out
    assert not roof_area(lean, below, 1.5, px).any()
    infill = below.copy()
    infill[98:102, 60:140] = True  # a sparse infill line (0.5 mm) crossing the gap
    assert not roof_area(infill, below, 1.5, px).any()
    lintel = below.copy()
    lintel[100:114, 60:140] = True  # a window's lintel: a wall 1.75 mm thick over the window
    assert roof_area(lintel, below, 1.5, px)[107, 80:120].all()
    assert not roof_area(below, below, 1.5, px).any()
    ring = np.zeros_like(below)
    ring[40:160, 20:180] = True
    ring[60:140, 40:160] = False  # perimeters round sparse infill's pocket ...
    skin = np.zeros_like(below)
    skin[40:160, 20:180] = True  # ... closed by a top skin: no camera sees under it
    assert not roof_area(skin, ring, 1.5, px).any()
    skin[100:104, 180:220] = True  # the same skin with a bridge out of its side is a roof there, and only there
    assert not roof_area(skin, ring, 1.5, px).any()  # (a bead-wide one is not)
    skin[90:114, 180:220] = True
    got = roof_area(skin, ring, 1.5, px)
    assert got[100, 195:218].all() and not got[:, :190].any()


def test_outside_the_zone_nothing_is_explained():
    E = _shadow(_surface(), 0.6, x0=104)
    photo = _noisy(_shadow(_surface(), 0.6, x0=100), 1)
    change, shaded = _judge(photo, _noisy(E, 2), np.zeros((H, W), bool))
    assert change.changed.any() and not shaded.any()


def test_a_strand_of_another_colour_is_not_shade():
    """A grey-white strand over the orange floor: its gains differ between the channels."""
    E = _surface()
    photo = E.copy()
    yy, xx = np.mgrid[0:H, 0:W]
    strand = np.abs(yy - (40 + 0.4 * xx)) < 2.5
    photo[strand] = (150.0, 150.0, 150.0)
    change, shaded = _judge(_noisy(photo, 1), _noisy(E, 2), np.ones((H, W), bool))
    assert change.changed.sum() >= 5 and not shaded.any()


def test_a_strand_of_the_floors_own_colour_keeps_its_texture_and_is_not_shade():
    """An orange strand on the orange floor (grey gain): its own highlights and shade lines remain."""
    E = _surface()
    photo = E.copy()
    yy, xx = np.mgrid[0:H, 0:W]
    d = yy - (40 + 0.4 * xx)
    for off in (0.0, 5.0, 10.0, 15.0):  # a few loops of filament, lit on top and dark at their edges
        dd = np.abs(d - off)
        photo = np.where((dd < 2.0)[..., None], photo * np.where(dd < 1.0, 1.3, 0.5)[..., None], photo)
    change, shaded = _judge(_noisy(np.clip(photo, 0, 255), 1), _noisy(E, 2), np.ones((H, W), bool))
    assert change.changed.sum() >= 5
    assert shaded.sum() <= 0.2 * change.changed.sum()


def test_a_dark_object_deeper_than_any_shadow_is_not_shade():
    E = _surface(rgb=(1.0, 0.95, 0.9), level=120.0)
    photo = E.copy()
    photo[60:100, 80:140] *= 0.5 * MIN_GAIN  # a black lump on a grey sheet
    change, shaded = _judge(_noisy(photo, 1), _noisy(E, 2), np.ones((H, W), bool))
    assert change.changed.sum() >= 20 and not shaded.any()


def test_a_bright_screw_on_a_dark_sheet_is_not_a_shadow_receding():
    E = _surface(rgb=(1.0, 0.95, 0.9), level=30.0)
    photo = E.copy()
    photo[60:100, 80:140] = np.clip(photo[60:100, 80:140] * 5.0, 0, 255)
    change, shaded = _judge(_noisy(photo, 1), _noisy(E, 2), np.ones((H, W), bool))
    assert change.changed.sum() >= 20 and not shaded.any()


def test_a_clipped_red_channel_is_left_out_and_the_shade_still_explained():
    """A lit orange floor whose red channel clipped: the shade shows in green and blue (red is gone from the fit)."""
    E = _surface(rgb=(1.0, 0.6, 0.25), level=200.0)
    E[..., 0] = 255.0  # clipped all over
    E = _shadow(E, 0.6, x0=104)
    E[..., 0] = 255.0
    photo = _noisy(_shadow(_surface(rgb=(1.0, 0.6, 0.25), level=200.0), 0.6, x0=100), 1)
    photo[..., 0] = 255.0  # still clipped in the shade (the red channel's true value is above 255 / 0.6)
    scored = np.ones((H, W), bool)
    ratio = np.ones((H, W, 3), np.float32)
    clipped = np.zeros((H, W, 3), bool)
    clipped[..., 0] = True
    change = change_blocks(photo, E, scored, ratio, SceneSettings(enabled=True), expected_clipped=clipped)
    shaded = explained_by_shade(change, photo, E.copy(), scored, np.ones((H, W), bool), clipped)
    assert change.changed.sum() >= 3
    assert shaded.sum() >= 0.9 * change.changed.sum()


@pytest.mark.parametrize("value", ["-1.0", "25.0", "nan"])
def test_a_shadow_reach_out_of_range_is_refused_naming_the_setting(tmp_path, value):
    from layerwatch.errors import ConfigError
    from layerwatch.pipeline.config import load_config

    job = tmp_path / "job.toml"
    job.write_text(f"[scene]\nshadow_reach = {value}\n")
    with pytest.raises(ConfigError, match="shadow_reach") as err:
        load_config(job)
    assert "\n" not in str(err.value).strip()
