"""Cast shadows of the printed part: changes beside the print that only the light explains.

A lamp beside the camera throws the part's shadow onto the bed and onto the
part's own lower floors. The shadow grows with every layer (a wall ``dz``
taller throws a shadow ``dz cot(elevation)`` longer) and moves when the lamp
sways, so the scene channel (:mod:`layerwatch.analysis.scene_change`), which
asks every pixel outside the predicted change ``M_k`` to look as it did, sees
blocks next to the part change on clean layers. On Blender Cycles photos of a
clean print of the bundled part (session 20) that was 17 of 33 layers with a
change "beside the print", and none once the lamp cast no shadows; the
simulator's raster photos have no cast shadows, which is how it went unseen.

A changed block (:class:`~layerwatch.analysis.scene_change.ChangeMap`) is
taken as shade, not material, when all of these hold:

1. **Within the shadow's reach** (:func:`shadow_zone`): at most
   ``shadow_reach`` times the print's height from the printed body in the
   image (``shadow_reach`` is the cotangent of the lowest lamp elevation
   allowed for; 2 covers a lamp 27 deg above the bed and higher). Nothing far
   from the part is ever explained away.
2. **Grey**: its per-channel gains against the prediction (least squares over
   its usable pixels) agree within :data:`GREY_SPREAD`: removing or returning
   a lamp's light scales the three channels alike, a strand or an object of
   another colour does not.
3. **In a shadow's range**: every gain within [:data:`MIN_GAIN`,
   1 / :data:`MIN_GAIN`], the block's and each pixel's (median-filtered): a
   shadow keeps the ambient light, and a bright screw on a dark sheet (a gain
   of 5-7) is not a shadow receding, not even in a block it half covers.
4. **Texture kept**: after a per-pixel grey gain, median-filtered over
   :data:`MEDIAN_PX` px (a shadow's edge is a step the median keeps; a strand
   one or two pixels wide is removed from it), the block's mean residual is
   below :data:`TEXTURE_K` times the frame's change threshold: the surface under the shade is the one
   ``E`` showed. Clipped channels are left out channel by channel.
5. **One way**: its pixels darken or brighten, not
   both: at most :data:`ONE_WAY_SHARE` of them move, by more than
   :data:`ONE_WAY_LOG` in log (or 2.5 sigma of the frame's noise), against the others. A
   shade coming or going (soft-edged or sharp) moves every pixel it touches
   the same way; a clump of strands of the floor's own colour, lit on top and
   dark between, moves some up and some down. And at most :data:`EDGE_SHARE`
   of them move at all: between two photos a shadow's edge advances across a
   block by the new layer's height (or the lamp's sway); a clump of strands
   that lands on the floor covers all of it (on the simulator a same-colour
   clump on the plate darkened 85-91 % of its blocks' pixels, one way; the
   Cycles shadows of a clean print moved 52 % at the median, 11 % of them
   over 0.8). **Under a roof** of the part (:func:`roof_area`: a bridge's deck,
   an overhang's ledge, a window's lintel: material printed over air) the
   shade does cover whole blocks at once (the deck closing over the bed
   under it, the lamp's sway moving the deck's shadow across the opening),
   so there (:func:`explained_by_shade`'s ``whole``) the block may move
   entirely; it must still move one way, grey, within a shadow's range, with
   its texture kept. On the Cycles photos of the window part (session 21) the
   bed under its bridge's deck darkened to 0.41-0.68 on 85-100 % of its
   blocks' pixels from the deck's first layer on.

What it gives up: a grey object of the bed's own texture, within the shadow's
reach, whose interior is uniform, is taken as shade (its outline usually is
not); the HOG channel still judges the layer's own footprint.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.analysis.block_masks import touching
from layerwatch.analysis.scene_change import SATURATED, ChangeMap

__all__ = ["GREY_SPREAD", "MEDIAN_PX", "MIN_GAIN", "EDGE_SHARE", "ONE_WAY_LOG", "ONE_WAY_SHARE", "TEXTURE_K", "explained_by_shade",
           "ROOF_MIN_WIDTH_MM", "roof_area", "shadow_zone"]

#: largest ratio between a block's largest and smallest channel gain that a shade may have
GREY_SPREAD = 1.3
#: smallest gain a cast shadow leaves (the ambient and fill stay): 1 / this is the largest
MIN_GAIN = 0.35
#: the texture test's limit, in the frame's change thresholds: a shadow's edge resampled into the working
#: image leaves a residual of 1-2 thresholds; a strand or an object's outline leaves more
TEXTURE_K = 1.5
#: test 5: a pixel moved by more than this log gain (~ 5 %, or the frame's noise when larger) moved;
#: at most this share of the block's pixels may move against the others
ONE_WAY_LOG = 0.05
ONE_WAY_SHARE = 0.05
#: test 5: at most this share of a block's pixels moved: between two photos a shadow's edge advances by
#: the new layer's height (or the lamp's sway) across a block; a clump of strands lands on all of it
EDGE_SHARE = 0.8
#: window of the median over the per-pixel gain, working px (3 or 5: OpenCV's float median)
MEDIAN_PX = 5
#: a roof (:func:`roof_area`) is at least this wide, mm: a sparse infill line crossing the gap between the lines
#: below is a bead (~0.4-0.6 mm) wide; a window's lintel is a wall's thickness
ROOF_MIN_WIDTH_MM = 1.0


def shadow_zone(body: np.ndarray, reach_px: float) -> np.ndarray:
    """Pixels within ``reach_px`` of the printed body (where its cast shadow may fall), bool (h, w).

    Parameters
    ----------
    body : ndarray, bool, shape (h, w)
        The printed body as the camera sees it (working image).
    reach_px : float
        Largest distance from the body, working px (Euclidean).

    Returns
    -------
    ndarray, bool, shape (h, w)
        The body itself included; all False when the body is empty or ``reach_px <= 0``.
    """
    if reach_px <= 0 or not body.any():
        return np.zeros(body.shape, bool)
    dist = cv2.distanceTransform(np.where(body, 0, 255).astype(np.uint8), cv2.DIST_L2, 3)
    return dist <= float(reach_px)


def roof_area(footprint: np.ndarray, below: np.ndarray, margin_mm: float, px_per_mm: float) -> np.ndarray:
    """Where a layer is printed over air: a roof of the part (a bridge's deck, an overhang's ledge, a lintel).

    The layer's footprint farther than ``margin_mm`` from the layer below's (a wall that leans out by
    a bead a layer is no roof), opened by a disc :data:`ROOF_MIN_WIDTH_MM` wide (nor is a sparse
    infill line crossing the gap between the lines below), in pieces that reach the layer's outline:
    the air under them is open to the side, so the camera may see the floor under them. A top skin
    over sparse infill closes its pockets on every side (on the bundled part: 24 of its 25 pieces of
    layer 10, every piece of layer 30); no camera sees under it.

    Parameters
    ----------
    footprint, below : ndarray, bool, shape (H, W)
        Top-view footprints of the layer and of the layer under it.
    margin_mm : float
        How far a layer may stand out of the one below and still rest on it, mm.
    px_per_mm : float
        Top-view scale.

    Returns
    -------
    ndarray, bool, shape (H, W)
    """
    def disc(mm: float) -> np.ndarray:
        k = max(int(round(float(mm) * float(px_per_mm))) | 1, 3)
        return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))

    fp, under = np.asarray(footprint, bool), np.asarray(below, bool)
    if not (fp & ~under).any():  # (most layers: the footprint of the one below, or less)
        return np.zeros(fp.shape, bool)
    over_air = fp & ~cv2.dilate(under.view(np.uint8), disc(2 * margin_mm)).astype(bool)
    roof = cv2.morphologyEx(over_air.view(np.uint8), cv2.MORPH_OPEN, disc(ROOF_MIN_WIDTH_MM))
    if not roof.any():
        return roof.astype(bool)
    rim = cv2.dilate((~fp).view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)  # next to the outside
    return touching(roof, rim)


def _one_way(ratio: np.ndarray, tol: float, edge_share: float = EDGE_SHARE) -> bool:
    """Whether ``ratio`` (the pixels' gains, (k,)) only darkens or only brightens, beyond ``tol`` in log, with at
    most ``edge_share`` of them moved (test 5).

    A shade coming or going moves every pixel it touches the same way; a strand's or an object's own
    shading, lit on top and dark beside, moves some pixels up and others down.
    """
    lr = np.log(np.maximum(ratio, 1e-3))
    up, down = float((lr > tol).mean()), float((lr < -tol).mean())
    return min(up, down) <= ONE_WAY_SHARE and max(up, down) <= edge_share


def explained_by_shade(change: ChangeMap, photo: np.ndarray, pred: np.ndarray, scored: np.ndarray,
                       zone: np.ndarray, expected_clipped: np.ndarray | None = None,
                       whole: np.ndarray | None = None) -> np.ndarray:
    """The changed blocks that a cast shadow explains (the module's five tests).

    Channels the camera clipped (at :data:`~layerwatch.analysis.scene_change.SATURATED` or above in
    the photo, or clipped in ``E``) say nothing of a gain and are left out, channel by channel: a lit
    orange floor clips its red channel, its green and blue still show the shade.

    Parameters
    ----------
    change : ChangeMap
        The photo's change blocks (:func:`~layerwatch.analysis.scene_change.change_blocks`).
    photo, pred : ndarray, float32, shape (h, w, 3)
        The working image and its prediction ``min(ratio E, 255)``, grey levels.
    scored : ndarray, bool, shape (h, w)
        The pixels the blocks were scored on.
    zone : ndarray, bool, shape (h, w)
        :func:`shadow_zone`.
    expected_clipped : ndarray, bool, shape (h, w, 3), optional
        Channels of ``E`` the camera clipped (default: ``pred`` at or above ``SATURATED``).
    whole : ndarray, bool, shape (h, w), optional
        Under the part's roofs (module notes): a block at least half on it may move entirely (no
        :data:`EDGE_SHARE` cap). Default: nowhere.

    Returns
    -------
    ndarray, bool, shape (n, m)
        Changed blocks explained as shade (a subset of ``change.changed``).
    """
    b = change.block_px
    out = np.zeros(change.changed.shape, bool)
    h, w = scored.shape
    pad = MEDIAN_PX // 2
    # 2.5 sigma of a pixel's gain: its grey level's noise is ~ 1.25 x the frame's median block score (a mean
    # absolute residual), over the grey level (module test 5)
    noise = 2.5 * 1.25 * float(np.median(change.score[change.scored])) if change.scored.any() else 0.0
    for r, c in zip(*np.nonzero(change.changed), strict=True):
        y0, x0 = r * b, c * b
        if zone[y0:y0 + b, x0:x0 + b].mean() < 0.5:
            continue
        ys, xs = slice(max(y0 - pad, 0), min(y0 + b + pad, h)), slice(max(x0 - pad, 0), min(x0 + b + pad, w))
        img, prd = photo[ys, xs].astype(np.float64), pred[ys, xs].astype(np.float64)
        clip = (img >= SATURATED) | (prd >= SATURATED)
        if expected_clipped is not None:
            clip |= expected_clipped[ys, xs]
        valid = scored[ys, xs][..., None] & ~clip  # (p, q, 3)
        inner = (slice(y0 - ys.start, y0 - ys.start + b), slice(x0 - xs.start, x0 - xs.start + b))
        v_in = valid[inner]
        counts = v_in.sum((0, 1))
        use = counts >= b * b // 4  # channels that can tell a gain
        if use.sum() < 2:
            continue
        g = ((img[inner] * prd[inner] * v_in).sum((0, 1)) / np.maximum((prd[inner] ** 2 * v_in).sum((0, 1)), 1e-6))[use]
        if g.min() < MIN_GAIN or g.max() > 1.0 / MIN_GAIN or g.max() > GREY_SPREAD * g.min():
            continue
        wv = valid * use
        ratio = ((img * wv).sum(-1) + 1.0) / ((prd * wv).sum(-1) + 1.0)
        raw = np.where(wv.any(-1), ratio, float(g.mean())).astype(np.float32)
        smooth = cv2.medianBlur(raw, MEDIAN_PX)
        wi = wv[inner]
        seen = wi.any(-1)  # the block's pixels with a channel that tells
        if smooth[inner][seen].min() < MIN_GAIN or smooth[inner][seen].max() > 1.0 / MIN_GAIN:  # deeper or brighter than a shade
            continue
        level = float((prd[inner] * wi).sum() / max(int(wi.sum()), 1))
        roofed = whole is not None and whole[y0:y0 + b, x0:x0 + b].mean() >= 0.5
        if not _one_way(raw[inner][seen], max(ONE_WAY_LOG, noise / max(level, 1.0)), 1.0 if roofed else EDGE_SHARE):
            continue
        res = np.abs(img - prd * smooth[..., None])[inner]
        out[r, c] = float((res * wi).sum() / max(int(wi.sum()), 1)) <= TEXTURE_K * change.threshold
    return out
