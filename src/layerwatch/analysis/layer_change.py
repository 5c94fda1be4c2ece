"""Changed as predicted: where the new layer was printed, the photo must have changed since the previous photo.

Series mode only (it needs the previous photo of the same print). The camera
is stationary, so between the photo of layer ``k`` and the previous analysed
photo (layer ``j < k``) every point of the new layer's footprint received new
plastic: its fine texture must differ. A patch missing from the infill or a
gap in a thin wall leaves the surface printed before in place, and the photo
shows there what the previous photo showed: **the same texture at the same
pixels**. That is what this channel looks for, per pixel of the layer's
footprint projected into the image on the layer's plane (the nothing-extruded
check's projection, :mod:`layerwatch.analysis.extrusion`, asks the same
question for the whole layer).

The comparison runs on the high-passed grey texture
(:func:`~layerwatch.analysis.extrusion.box_texture`: exposure drift, white
balance and a smooth change of light are a gain, which the high pass and the
normalisation remove), in a Gaussian window of ``window_px`` working pixels
around every footprint pixel (:func:`window_change`; a wall 0.45-1 mm wide is
3-7 px, narrower than any block):

* **noise aware**: the sensor noise, independent in the two photos, lowers
  the correlation of an unchanged surface. The noise variance ``n`` of the
  pair is half the median variance of ``a - b`` on quiet blocks of
  ``block_px`` (off the new layer's projection: bed, earlier surfaces, which
  did not change; :func:`pair_noise`); a pixel is judged only when the
  texture in its window stands above it (``>= (1 + min_snr) n`` in both
  photos) and at least :data:`OWN_SHARE` of that texture's energy lies on the
  footprint grown by :data:`OWN_GROW_PX` (on its edge a window can see mostly
  the unchanged surface beside it), and it reaches no clipped pixel of either
  photo (a glare spot of a fixed lamp stays in place from layer to layer,
  and its border is the light's, not the surface's).
* **against the printed twin**: a perimeter laid on its twin, or sparse infill
  repeating the line below, looks alike too, but one layer higher: the camera
  sees it shifted by the parallax of the height printed since the previous
  photo (:func:`parallax_px`). The window's NCC with the previous texture at
  the same pixels (``same``) is set against its NCC with the previous texture
  shifted by that parallax (``twin``; the better of the full parallax and
  ``1 - twin_tolerance`` of it: a bead's width and place vary by a tenth of a
  millimetre from layer to layer, which moves its edge against the rise). A
  pixel is judged only where the shift changes the previous texture
  (``1 - NCC(prev, shifted prev) >= min_parallax_change``: a bead running
  along the parallax direction looks the same shifted, so there the test
  cannot tell a gap from a twin), and it is *unchanged* when ``same >=
  min_ncc`` and ``same - twin >= min_gain``.
* **not a silhouette band** (:func:`drop_edge_slivers`): the footprint's
  edges across the parallax direction are silhouettes, the one facing the
  camera (a lower surface is seen beyond it) and the one facing away (what
  lies behind is seen beyond it). A bead a tenth of a millimetre wider than
  the one below, or placed that much off it, moves a silhouette against the
  rise's parallax (at 0.2 mm layers, 1 px of parallax, by about as much as
  the rise itself): the edge can look unchanged although the layer was
  printed, while the rest of the cross-section changed. An unchanged area
  that lies (80 %) within ``2 window_px`` of one silhouette, where the
  footprint goes on for at least ``window_px`` beyond it, is dropped (seen on
  the 1.8 mm walls of the evaluation's window part: the front wall's front
  edge, the back wall's far edge, 10-20 % of the judged pixels of a clean
  layer). A gap through a wall leaves its whole cross-section unchanged and
  is kept; a missing outer bead of a wide surface looks like the silhouette
  case and is not found.

Connected unchanged areas are carried to the top view of the layer's plane
(the pipeline's own warp maps), kept on the footprint, and those of at least
``min_area_mm2`` become failing regions, typed ``thin_wall`` or
``infill_defect`` by what the G-code prints there (:func:`printed_kind`).
Pixels too flat to judge (a dark filament, a black or missing previous photo)
give no verdict, never a failure. A gap is reported from its onset layer on:
the photo of the onset shows the layer below, one layer height lower, where
the plan put the new layer (0.3 mm: 1.5 px of parallax at the simulator's
camera, found by the twin test).

References
----------
Lewis (1995), "Fast normalized cross-correlation" (zero-mean NCC).
Petsiuk & Pearce (2022), eq. (5): a% = S_A / S_P.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

import cv2
import numpy as np
from pydantic import Field

from layerwatch.analysis.block_masks import block_tiles, components
from layerwatch.analysis.block_moments import block_moments
from layerwatch.analysis.region_outline import outline_mask
from layerwatch.analysis.result import LayerResult, Region
from layerwatch.analysis.scene_change import change_regions, top_coords
from layerwatch.analysis.scoring import anomaly_ratio
from layerwatch.gcode.toolpath import FEATURES, Toolpath
from layerwatch.geometry.topview import TopView
from layerwatch.settings_base import Section

__all__ = ["CLIP_LEVEL", "EDGE_DEPTH", "EDGE_SHARE", "OWN_GROW_PX", "OWN_SHARE", "LayerChangeSettings", "WindowChange", "add_unchanged", "apart_from", "blocks_on_top", "clipped_box", "drop_edge_slivers",
           "moved_pixels", "pair_noise", "parallax_px", "printed_kind", "unchanged_regions", "window_change"]

#: quiet blocks need this much texture variance (grey levels^2) in both photos to calibrate the noise on
QUIET_MIN_VAR = 1.0
#: fewest quiet blocks to calibrate on; fewer: the pair is not judged
MIN_QUIET_BLOCKS = 20
#: share of a window's texture energy that must lie on the footprint for the pixel to be judged (:func:`window_change`)
OWN_SHARE = 0.5
#: a photo pixel at this level or above in every channel is clipped: a glare spot (:func:`clipped_box`)
CLIP_LEVEL = 250
#: the footprint grown by this (working px) for :data:`OWN_SHARE` (its edges and their blur are its own texture)
OWN_GROW_PX = 2
#: share of an unchanged area within the camera-facing edge band of a wider surface that drops it (:func:`drop_edge_slivers`)
EDGE_SHARE = 0.8
#: the footprint must go on this far (in window sigmas) beyond a silhouette band's pixel for the band to be a sliver (:func:`drop_edge_slivers`)
EDGE_DEPTH = 1.0
#: segment features that are walls / infill (the kind of an unchanged region, :func:`printed_kind`)
_WALLS = tuple(FEATURES.index(n) for n in ("perimeter", "external_perimeter"))
_INFILL = tuple(FEATURES.index(n) for n in ("infill", "solid_infill", "top_solid_infill", "bridge"))


class LayerChangeSettings(Section):
    """The "changed as predicted" channel (config section ``[layer_change]``; series mode only).

    Off in the built-in (paper) values, on in the recommended ones
    (:data:`layerwatch.pipeline.config.RECOMMENDED`), so ``--paper-settings``
    reproduces the paper's method. It compares textures on the nothing-extruded
    check's working image (``[extrusion] working_px``).

    Attributes
    ----------
    enabled : bool
        Look for footprint areas that did not change since the previous photo.
    min_area_mm2 : float
        Smallest connected unchanged area of the footprint that fails, mm^2 on the layer's plane.
    min_ncc : float
        Window NCC at the same pixels from which a pixel is unchanged.
    min_gain : float
        How much that correlation must exceed the correlation with the previous
        texture shifted by the layer's parallax (a twin printed on top).
    twin_tolerance : float
        The twin is also tried shifted by ``1 - twin_tolerance`` of the parallax (an edge
        bead a little wider or displaced toward the camera); the better NCC counts.
    wall_run_mm : float
        On the G-code's perimeters a pixel that passes the looser ``wall_min_ncc`` /
        ``wall_min_gain`` is unchanged too when it lies in a run along the wall at least this
        long, mm on the layer's plane (:mod:`layerwatch.analysis.wall_runs`); 0: off.
    wall_min_ncc, wall_min_gain : float
        ``min_ncc`` and ``min_gain`` for the perimeter pixels of such runs.
    min_parallax_change : float
        ``1 - NCC`` of the previous texture with itself shifted by the parallax that a
        pixel's window needs to be judged (below it the twin test cannot decide).
    min_snr : float
        Texture energy above the noise a window needs, in units of the noise variance.
    window_px : float
        Gaussian sigma of the comparison window, px of the working image.
    block_px : int
        Block side of the noise calibration on quiet blocks, px of the working image.
    """

    enabled: bool = False
    min_area_mm2: float = Field(0.5, ge=0, le=2500)
    min_ncc: float = Field(0.8, ge=0, le=1)
    min_gain: float = Field(0.1, ge=0, le=2)
    twin_tolerance: float = Field(0.3, ge=0, lt=1)
    wall_run_mm: float = Field(2.5, ge=0, le=100)
    wall_min_ncc: float = Field(0.7, ge=0, le=1)
    wall_min_gain: float = Field(0.05, ge=0, le=2)
    min_parallax_change: float = Field(0.2, ge=0, le=2)
    min_snr: float = Field(1.0, ge=0, le=100)
    window_px: float = Field(3.0, ge=0.5, le=16)
    block_px: int = Field(8, ge=2, le=64)


@dataclass
class WindowChange:
    """One photo pair's verdict per pixel of the footprint's box (shape ``(h, w)`` = the working box).

    Attributes
    ----------
    same, twin : ndarray, float32, shape (h, w)
        Window NCC with the previous texture at the same pixels, and shifted by
        the parallax (0 where not judged).
    judged : ndarray, bool, shape (h, w)
        Footprint pixels whose window has texture above the noise that the parallax changes.
    unchanged : ndarray, bool, shape (h, w)
        Judged pixels that look as in the previous photo.
    noise : float
        Noise variance of one photo's texture, grey levels^2.
    """

    same: np.ndarray
    twin: np.ndarray
    judged: np.ndarray
    unchanged: np.ndarray
    noise: float


def _block_sum(v: np.ndarray, bp: int) -> np.ndarray:
    """Per-block mean of ``v`` (h, w) over whole ``bp`` blocks: (h // bp, w // bp) float32."""
    n, m = v.shape[0] // bp, v.shape[1] // bp
    return cv2.resize(np.ascontiguousarray(v[: n * bp, : m * bp], np.float32), (m, n), interpolation=cv2.INTER_AREA)


def _moments(a: np.ndarray, b: np.ndarray, bp: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-block variances of ``a`` and ``b`` and their covariance (whole blocks)."""
    ma, mb, maa, mbb, mab = block_moments(a, b, bp)  # the five block means in one pass (OpenCV's values)
    return np.maximum(maa - ma * ma, 0), np.maximum(mbb - mb * mb, 0), mab - ma * mb


def parallax_px(maps: tuple[np.ndarray, np.ndarray], z: float, dz: float, step: int = 4) -> tuple[float, float]:
    """Image shift (working px) of a surface raised by ``dz`` mm at height ``z``: ``(dx, dy)``.

    A point seen at pixel ``p`` on the plane ``z`` is seen at ``p + d`` on the
    plane ``z - dz``: ``d = J^-1 (dT/dz) dz``, with ``J`` the top-view px per
    image px and ``dT/dz`` the top-view shift of a pixel's ray per mm of
    height (medians over every ``step``-th pixel of ``maps``: the print's box
    is small against its distance to the camera, so one shift serves it).

    Parameters
    ----------
    maps : (ndarray, ndarray)
        :func:`~layerwatch.analysis.scene_change.plane_maps` of the working box.
    z, dz : float
        Height of the new surface and the height printed since the previous photo, mm.
    step : int
        Subsampling of the medians, px.
    """
    A, B = (np.asarray(m)[:, ::step, ::step] for m in maps)
    tx, ty = top_coords((A, B), z)
    if tx.shape[0] < 2 or tx.shape[1] < 2 or dz == 0:
        return 0.0, 0.0
    J = np.array([[np.median(np.diff(tx, axis=1)), np.median(np.diff(tx, axis=0))],
                  [np.median(np.diff(ty, axis=1)), np.median(np.diff(ty, axis=0))]], np.float64) / step
    dT = np.array([np.median(B[0]), np.median(B[1])], np.float64) * dz
    if abs(np.linalg.det(J)) < 1e-9:
        return 0.0, 0.0
    d = np.linalg.solve(J, dT)
    return float(d[0]), float(d[1])


def _shifted(b: np.ndarray, d: tuple[float, float]) -> np.ndarray:
    """``b(p + d)`` (bilinear; borders replicated)."""
    M = np.array([[1.0, 0.0, d[0]], [0.0, 1.0, d[1]]], np.float32)
    return cv2.warpAffine(b, M, (b.shape[1], b.shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


def _aligned_box(mask: np.ndarray, grow: int) -> tuple[slice, slice] | None:
    """Rows and columns of ``mask``'s bounding box grown by ``grow`` px, within the image (``None``: empty)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return (slice(max(int(rows[0]) - grow, 0), min(int(rows[-1]) + 1 + grow, mask.shape[0])),
            slice(max(int(cols[0]) - grow, 0), min(int(cols[-1]) + 1 + grow, mask.shape[1])))


def pair_noise(a: np.ndarray, b: np.ndarray, near: np.ndarray, block_px: int) -> float | None:
    """Noise variance of one photo's texture: half the median variance of ``a - b`` on quiet blocks.

    Quiet blocks lie off ``near`` (what the print may have changed) and have
    texture (variance above :data:`QUIET_MIN_VAR`) in both photos.

    Parameters
    ----------
    a, b : ndarray, float32, shape (h, w)
        High-passed textures of the new and the previous photo.
    near : ndarray, bool, shape (h, w)
    block_px : int

    Returns
    -------
    float or None
        ``None`` when fewer than :data:`MIN_QUIET_BLOCKS` blocks are quiet (a
        black, blank or foreign previous photo): the pair cannot be judged.
    """
    va, vb, cov = _moments(a, b, block_px)
    calm = (_block_sum(near.astype(np.float32), block_px) == 0) & (np.minimum(va, vb) > QUIET_MIN_VAR)
    if int(calm.sum()) < MIN_QUIET_BLOCKS:
        return None
    return 0.5 * float(np.median((va + vb - 2 * cov)[calm]))


def clipped_box(photo: np.ndarray, size: tuple[int, int], box: tuple[slice, slice]) -> np.ndarray:
    """Working-image pixels of ``box`` that touch a clipped photo pixel (every channel >= :data:`CLIP_LEVEL`).

    A glare spot is white (a specular reflection has the lamp's colour); a saturated colour
    clips one channel while the others still carry the texture, so it does not count.

    Parameters
    ----------
    photo : ndarray, uint8, shape (h, w) or (h, w, 3)
        Frame as captured.
    size : (int, int)
        Working ``(width, height)`` px.
    box : (slice, slice)
        Rows and columns of the working image (bounds within it).

    Returns
    -------
    ndarray, bool, shape (rows, cols)
    """
    arr = np.asarray(photo)
    h, w = arr.shape[:2]
    W, H = size
    (r0, r1), (c0, c1) = ((s.start or 0, n if s.stop is None else s.stop) for s, n in zip(box, (H, W), strict=True))
    y0, y1 = int(np.floor(r0 * h / H)), int(np.ceil(r1 * h / H))
    x0, x1 = int(np.floor(c0 * w / W)), int(np.ceil(c1 * w / W))
    crop = arr[y0:y1, x0:x1]
    lo = (CLIP_LEVEL,) * (crop.shape[2] if crop.ndim == 3 else 1)
    hot = cv2.inRange(crop, lo, (255,) * len(lo))  # 255 where every channel is clipped (one pass)
    out = np.zeros((r1 - r0, c1 - c0), bool)
    u, v, w, h = cv2.boundingRect(hot)
    if w == 0 or h == 0:
        return out
    # the share of each working pixel's source area that is clipped (area resize): any share counts.
    # Only the working rows whose source rows hold a clipped pixel can be set: resized alone when the rows'
    # scale is p / 2^k (every row weight an exact binary fraction, so they come out as in the whole resize)
    scale = Fraction(hot.shape[0], r1 - r0)
    q = scale.denominator
    i0, i1 = 0, r1 - r0
    if q & (q - 1) == 0:
        i0 = int(v / scale) // q * q
        i1 = min(-(-(int((v + h - 1) / scale) + 1) // q) * q, r1 - r0)
    band = hot[int(i0 * scale):int(i1 * scale)]
    out[i0:i1] = cv2.resize(band, (c1 - c0, i1 - i0), interpolation=cv2.INTER_AREA) > 0
    return out


def window_change(a: np.ndarray, b: np.ndarray, surface: np.ndarray, near: np.ndarray,
                  parallax: tuple[float, float], settings: LayerChangeSettings,
                  clipped: np.ndarray | None = None) -> WindowChange | None:
    """Which pixels of the new layer's projected footprint look as in the previous photo (module notes).

    Computed on the footprint's bounding box (grown by the window's reach) only.

    Parameters
    ----------
    a, b : ndarray, float32, shape (h, w)
        High-passed textures of the new and the previous photo (:func:`~layerwatch.analysis.extrusion.box_texture`).
    surface : ndarray, bool, shape (h, w)
        The new layer's footprint on its plane, seen through the camera.
    near : ndarray, bool, shape (h, w)
        Pixels the print may have changed since the previous photo (the new
        layer's projection with its walls, grown): never quiet.
    parallax : (float, float)
        :func:`parallax_px` of the height printed since the previous photo.
    settings : LayerChangeSettings
    clipped : ndarray, bool, shape (h, w), optional
        Pixels clipped in either photo (:func:`clipped_box`): a glare spot has no texture, and its
        border is the light's, which a fixed lamp keeps in place from layer to layer; pixels whose
        window reaches one (``2 window_px``) are not judged.

    Returns
    -------
    WindowChange or None
        ``None`` when the pair cannot be calibrated (:func:`pair_noise`).
    """
    noise = pair_noise(a, b, near, settings.block_px)
    if noise is None:
        return None
    shape = a.shape
    same, twin = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    judged, unchanged = np.zeros(shape, bool), np.zeros(shape, bool)
    sig = float(settings.window_px)
    box = _aligned_box(surface, int(np.ceil(3 * sig)))
    if box is None:
        return WindowChange(same, twin, judged, unchanged, noise)
    reach = int(np.ceil(max(abs(parallax[0]), abs(parallax[1])))) + 2  # the shifted crop's source pixels
    outer = _aligned_box(surface, int(np.ceil(3 * sig)) + reach)
    assert outer is not None
    inner = (slice(box[0].start - outer[0].start, box[0].stop - outer[0].start),
             slice(box[1].start - outer[1].start, box[1].stop - outer[1].start))
    x = np.ascontiguousarray(a[box], np.float32)
    y = np.ascontiguousarray(b[box], np.float32)
    b_outer = np.ascontiguousarray(b[outer], np.float32)  # the previous texture the shifted twins are cut from
    ys = np.ascontiguousarray(_shifted(b_outer, parallax)[inner])

    def g(v: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(v, (0, 0), sig)

    xx, yy, ss = g(x * x), g(y * y), g(ys * ys)
    tiny = 1e-6
    s_same = g(x * y) / np.sqrt(xx * yy + tiny)
    s_twin = g(x * ys) / np.sqrt(xx * ss + tiny)
    moved = 1.0 - g(y * ys) / np.sqrt(yy * ss + tiny)
    if settings.twin_tolerance > 0:  # an edge bead that grew toward the camera: the rise seen short
        k = 1.0 - settings.twin_tolerance
        yk = np.ascontiguousarray(_shifted(b_outer, (k * parallax[0], k * parallax[1]))[inner])
        s_twin = np.maximum(s_twin, g(x * yk) / np.sqrt(xx * g(yk * yk) + tiny))
    # the window's texture must be the footprint's own: on the footprint's edge a window that mostly sees
    # the unchanged surface beside it (a lower floor, the bed) would look unchanged although the layer was printed
    grow = 2 * OWN_GROW_PX + 1  # the footprint's own edges lie on its border, and the camera's blur spreads them
    m = cv2.dilate(surface[box].astype(np.uint8), np.ones((grow, grow), np.uint8)).astype(np.float32)
    own = np.minimum(g(m * x * x) / (xx + tiny), g(m * y * y) / (yy + tiny))
    ok = (surface[box] & (np.minimum(xx, yy) >= (1.0 + settings.min_snr) * noise)
          & (moved >= settings.min_parallax_change) & (own >= OWN_SHARE))
    if clipped is not None and clipped[box].any():
        reach = 2 * int(np.ceil(2 * sig)) + 1
        ok &= cv2.dilate(clipped[box].astype(np.uint8), np.ones((reach, reach), np.uint8)) == 0
    judged[box] = ok
    found = ok & (s_same >= settings.min_ncc) & (s_same - s_twin >= settings.min_gain)
    band = int(round(2 * sig))
    unchanged[box] = drop_edge_slivers(found, surface[box], parallax, band, max(1, int(round(EDGE_DEPTH * sig))))
    same[box], twin[box] = np.where(ok, s_same, 0), np.where(ok, s_twin, 0)
    return WindowChange(same, twin, judged, unchanged, noise)


def _line_kernel(direction: tuple[float, float], steps: range) -> tuple[np.ndarray, tuple[int, int]]:
    """A structuring element with ones at ``round(k * direction)`` for ``k`` in ``steps`` (anchor: the centre)."""
    r = max(abs(steps.start), abs(steps.stop)) + 1
    kern = np.zeros((2 * r + 1, 2 * r + 1), np.uint8)
    for k in steps:
        kern[r + int(round(k * direction[1])), r + int(round(k * direction[0]))] = 1
    return kern, (r, r)


def drop_edge_slivers(unchanged: np.ndarray, surface: np.ndarray, parallax: tuple[float, float],
                      band_px: int, depth_px: int) -> np.ndarray:
    """``unchanged`` without its areas that lie along a silhouette edge of the footprint (module notes).

    The footprint's edges across the parallax direction are silhouettes: the
    one facing the camera (a lower point is seen beyond it, in the parallax
    direction) and the one facing away (beyond it the camera sees what lies
    behind). Where a bead lies a tenth of a millimetre off the one below,
    either silhouette moves by about the rise's parallax against it, so it can
    stay in place although the layer was printed. An 8-connected unchanged
    area is dropped when at least :data:`EDGE_SHARE` of its pixels lie within
    ``band_px`` of one such edge while the footprint goes on for ``depth_px``
    from each of them the other way (the silhouette band is not the whole
    cross-section: the rest of it was seen to change). A gap through a wall
    (its whole cross-section unchanged) or a patch inside a surface stays.

    Parameters
    ----------
    unchanged, surface : ndarray, bool, shape (h, w)
    parallax : (float, float)
        Image shift of a lower surface, px (:func:`parallax_px`); zero: nothing dropped.
    band_px, depth_px : int

    Returns
    -------
    ndarray, bool, shape (h, w)
    """
    norm = float(np.hypot(*parallax))
    if norm < 1e-6 or not unchanged.any() or band_px < 1:
        return unchanged
    sm = surface.astype(np.uint8)
    n, lab = cv2.connectedComponents(unchanged.astype(np.uint8), connectivity=8)
    total = np.bincount(lab.ravel(), minlength=n)
    drop = np.zeros(n, bool)
    for sign in (1.0, -1.0):  # the edge facing the camera, then the one facing away
        u = (sign * parallax[0] / norm, sign * parallax[1] / norm)
        k_front, a_front = _line_kernel(u, range(1, band_px + 1))
        k_back, a_back = _line_kernel(u, range(-depth_px, 0))
        # erode: min over the kernel's offsets, so 1 where the footprint holds at every step (outside the image: not)
        front_held = cv2.erode(sm, k_front, anchor=a_front, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
        back_held = cv2.erode(sm, k_back, anchor=a_back, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
        sliver = ~front_held & back_held
        edge = np.bincount(lab[sliver & unchanged].ravel(), minlength=n)
        drop |= edge >= EDGE_SHARE * np.maximum(total, 1)
    drop[0] = False
    return unchanged & ~drop[lab]


def blocks_on_top(blocks: np.ndarray, block_px: int, origin: tuple[int, int], scale: tuple[float, float],
                  source: tuple[np.ndarray, np.ndarray], where: np.ndarray) -> np.ndarray:
    """Top-view pixels whose source pixel in the working image lies in a True block.

    Parameters
    ----------
    blocks : ndarray, bool, shape (n, m)
        Blocks of ``block_px`` working px, the first one's corner at ``origin``.
    block_px : int
    origin : (int, int)
        Row and column of the blocks' corner in the working image, px.
    scale : (float, float)
        Working px per photo px, x and y.
    source : (ndarray, ndarray), float32, shape (H, W)
        Photo px ``(x, y)`` seen at each top-view pixel on the layer's plane
        (the pipeline's warp maps, :meth:`~layerwatch.geometry.warp.TopViewWarper.maps`).
    where : ndarray, bool, shape (H, W)
        Top-view pixels to look up (the footprint, seen by the camera).

    Returns
    -------
    ndarray, bool, shape (H, W)
    """
    out = np.zeros(where.shape, bool)
    vv, uu = np.nonzero(where)
    if vv.size == 0 or not blocks.any():
        return out
    wx = (source[0][vv, uu] + 0.5) * scale[0] - origin[1]  # working px (pixel i spans [i, i + 1))
    wy = (source[1][vv, uu] + 0.5) * scale[1] - origin[0]
    bi, bj = np.floor(wy / block_px).astype(np.int64), np.floor(wx / block_px).astype(np.int64)
    ok = (bi >= 0) & (bi < blocks.shape[0]) & (bj >= 0) & (bj < blocks.shape[1])
    out[vv[ok], uu[ok]] = blocks[bi[ok], bj[ok]]
    return out


def printed_kind(toolpath: Toolpath, index: int, mask: np.ndarray, topview: TopView) -> str:
    """``"thin_wall"`` when walls are most of what layer ``index`` prints inside the top-view ``mask``, else ``"infill_defect"``.

    Segments count by their length inside the mask (sampled every top-view pixel).
    """
    sl = toolpath.layer_slice(index)
    p0, p1 = toolpath.start[sl][:, :2], toolpath.end[sl][:, :2]
    feats = toolpath.feature[sl]
    use = np.isin(feats, _WALLS + _INFILL)
    if not use.any():
        return "infill_defect"
    p0, p1, feats = p0[use], p1[use], feats[use]
    steps = np.maximum(1, np.ceil(np.hypot(*(p1 - p0).T) * topview.px_per_mm)).astype(int)
    seg = np.repeat(np.arange(len(p0)), steps)
    t = (np.arange(seg.size) - np.repeat(np.cumsum(steps) - steps, steps) + 0.5) / np.repeat(steps, steps)
    uv = np.round(topview.to_px(p0[seg] + t[:, None] * (p1 - p0)[seg])).astype(int)
    h, w = mask.shape
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    hit = np.zeros(seg.size, bool)
    hit[ok] = mask[uv[ok, 1], uv[ok, 0]]
    walls = int(np.isin(feats[seg[hit]], _WALLS).sum())
    return "thin_wall" if walls > hit.sum() - walls else "infill_defect"


def unchanged_regions(unchanged_top: np.ndarray, footprint: np.ndarray, toolpath: Toolpath, index: int,
                      topview: TopView, min_area_mm2: float) -> tuple[np.ndarray, list[Region]]:
    """The connected unchanged areas of the footprint, as typed failing regions.

    Parameters
    ----------
    unchanged_top : ndarray, bool, shape (H, W)
        Top-view pixels (plane of layer ``index``) whose block was unchanged.
    footprint : ndarray, bool, shape (H, W)
        The layer's footprint.
    toolpath : Toolpath
    index : int
        The layer.
    topview : TopView
    min_area_mm2 : float
        Smaller areas are dropped.

    Returns
    -------
    mask : ndarray, bool, shape (H, W)
        Pixels of the kept regions.
    regions : list of Region
        Largest first; ``kind`` ``"thin_wall"`` or ``"infill_defect"``
        (:func:`printed_kind`), ``kind_confidence`` the share of the region's
        footprint found unchanged, ``outside_fraction`` 0.
    """
    on = unchanged_top & footprint
    _, lab, stats, (v0, u0) = components(on)
    area = stats[:, cv2.CC_STAT_AREA] / topview.px_per_mm**2
    keep = np.flatnonzero(area >= min_area_mm2)
    keep = keep[keep > 0]
    mask = np.zeros(on.shape, bool)
    if keep.size:
        mask[v0 : v0 + lab.shape[0], u0 : u0 + lab.shape[1]] = np.isin(lab, keep)
    sim = np.where(mask, 0.0, 1.0).astype(np.float32)
    regions = change_regions(mask, sim, topview, min_area_mm2)
    for r in regions:
        x0, y0, x1, y1 = r.bbox_mm
        (u0, v0), (u1, v1) = np.round(topview.to_px(np.array([[x0, y1], [x1, y0]], float))).astype(int)
        box = (slice(max(v0, 0), v1 + 1), slice(max(u0, 0), u1 + 1))
        r.kind = printed_kind(toolpath, index, _crop_mask(mask, box), topview)
        fp = int(np.count_nonzero(footprint[box]))
        r.kind_confidence = round(float(np.count_nonzero(mask[box])) / max(fp, 1), 3)
        r.outside_fraction = 0.0
    return mask, regions


def _crop_mask(mask: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    out = np.zeros_like(mask)
    out[box] = mask[box]
    return out


def moved_pixels(regions: list[Region], topview: TopView) -> np.ndarray:
    """The top-view pixels a moved part's regions mark, bool (H, W).

    Each region's :attr:`~layerwatch.analysis.result.Region.outline_mm` (for a layer
    shift or a detachment: where the layer is and should not be, and where it should
    be and is not), or its box when it has none.
    """
    out = np.zeros((int(topview.shape[0]), int(topview.shape[1])), bool)
    for r in regions:
        if r.outline_mm:
            out |= outline_mask(r.outline_mm, topview)
            continue
        x0, y0, x1, y1 = r.bbox_mm
        (u0, v0), (u1, v1) = np.round(topview.to_px(np.array([[x0, y1], [x1, y0]], float))).astype(int)
        out[max(v0, 0): max(v1 + 1, 0), max(u0, 0): max(u1 + 1, 0)] = True
    return out


def apart_from(unchanged_top: np.ndarray, moved: np.ndarray, grow_mm: float, topview: TopView) -> np.ndarray:
    """``unchanged_top`` without the pixels within ``grow_mm`` of ``moved``, bool (H, W).

    Parameters
    ----------
    unchanged_top : ndarray, bool, shape (H, W)
        Unchanged top-view pixels.
    moved : ndarray, bool, shape (H, W)
        Pixels a moved part explains (:func:`moved_pixels`).
    grow_mm : float
        Margin around ``moved``, mm (a disc).
    topview : TopView
    """
    if not moved.any():
        return np.asarray(unchanged_top, bool)
    k = 2 * int(round(grow_mm * topview.px_per_mm)) + 1
    near = cv2.dilate(moved.view(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0
    return np.asarray(unchanged_top, bool) & ~near


def add_unchanged(res: LayerResult, mask: np.ndarray, regions: list[Region], topview: TopView) -> float:
    """Count the unchanged regions into ``res``: its ``regions`` and a% (eq. 5 over the printed area).

    ``S_A`` grows by the area of ``mask`` that no anomalous HOG block's tile
    already covers (each printed square counts once); ``S_P`` is unchanged.

    Parameters
    ----------
    res : LayerResult
        An analysed layer (``heatmap``, ``mask`` and ``grid`` of its comparison).
    mask : ndarray, bool, shape (H, W)
        Top-view pixels of ``regions``.
    regions : list of Region
    topview : TopView

    Returns
    -------
    float
        The area added to ``S_A``, mm^2.

    References
    ----------
    Petsiuk & Pearce (2022), eq. (5).
    """
    if not regions:
        return 0.0
    covered = np.zeros(mask.shape, bool)
    if res.heatmap is not None and res.mask is not None and res.grid is not None:
        anom = np.asarray(res.mask, bool) & (np.asarray(res.heatmap) < res.threshold)
        covered = block_tiles(anom, mask.shape, res.grid.cell_px, res.grid.block_cells, fill=False).astype(bool)
    added = float(np.count_nonzero(mask & ~covered)) / topview.px_per_mm**2
    res.anomalous_area_mm2 = float(res.anomalous_area_mm2) + added
    res.anomaly_ratio = anomaly_ratio(1, res.anomalous_area_mm2, float(res.printed_area_mm2))
    res.regions = sorted([*res.regions, *regions], key=lambda r: -r.area_mm2)
    return added
