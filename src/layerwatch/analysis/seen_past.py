"""What the previous photo saw past the part, where the new layer now stands.

The camera looks down at the print from one side. Beyond the part's far
silhouette a photo shows what lies behind: the bed, a skirt or brim line,
another object. When the part rises by ``dz`` between two photos, its far silhouette
climbs in the image and hides a band of what lay behind; at those pixels the
previous photo showed something *not of this column of the part*, which
neither stays in place (the "same" hypothesis of a gap) nor moves by the
rise's parallax (the "printed twin" hypothesis) in any predictable way.

Where that band held texture (a skirt line a few mm behind the far wall:
Simplify3D 4.1.2's ``skirtOffset,2``, Slic3r 1.3.1's ``skirt_distance = 6``),
the new wall's silhouette lands on the pixels where the hidden line had been,
with the same bright-over-dark profile, and a texture comparison of the two
photos reads the printed wall as unchanged (Simplify3D ``zlift``: the disc's
far wall hides its skirt while it rises from 1.8 to 3.4 mm, 14-34 mm^2 of
"thin-wall gap" on clean layer 13 of three prints). This module finds what the
previous photo saw past the part: pixels whose ray misses the part's outer
outline (:func:`outline_of`: the footprint closed, its enclosed areas filled,
so infill cells and holes are the part's own) both at the previous top and on
the bed (the part's own faces are not past it), :data:`EDGE_PX` off the part's
projection (the high pass spreads a bright edge onto the bed beside it). A
footprint pixel whose comparison window took at least :data:`BLIND_SHARE` of
its previous texture energy from there, and more than the texture test's
noise floor, is not to be judged.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.analysis.block_masks import fill_holes
from layerwatch.analysis.scene_change import top_coords
from layerwatch.geometry.topview import TopView

__all__ = ["BLIND_SHARE", "CLOSE_MM", "EDGE_PX", "outline_of", "past_share", "seen_past"]

#: the footprint closed by this (mm), its enclosed areas filled, is the part's outer outline: a
#: perimeter loop's raster gaps are sealed, sparse infill's cells and holes are inside the part
#: (a ray landing in one sees the part's own floor or inner face, which the comparison allows for)
CLOSE_MM = 2.0
#: a window with this share of its previous texture energy in the band seen past the part is not judged
BLIND_SHARE = 0.25
#: the band keeps this far (working px) from the part's projection: the high pass spreads a bright
#: edge's energy over the bed beside it (the texture test's own allowance, ``layer_change.OWN_GROW_PX``)
EDGE_PX = 2


def outline_of(footprint: np.ndarray, topview: TopView, close_mm: float = CLOSE_MM) -> np.ndarray:
    """The part's outer outline on a layer: ``footprint`` closed by ``close_mm``, enclosed areas filled.

    Parameters
    ----------
    footprint : ndarray, bool, shape (H, W)
        Top-view footprint (``topview`` geometry).
    topview : TopView
    close_mm : float

    Returns
    -------
    ndarray, bool, shape (H, W)
        Everything not reachable from the view's border without crossing the closed footprint
        (a notch open to the outside stays outside; each object of a plate has its own outline).
    """
    k = int(round(close_mm * topview.px_per_mm)) | 1
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    fp = (np.asarray(footprint) != 0).astype(np.uint8)
    out = np.zeros(fp.shape, bool)
    u, v, w, h = cv2.boundingRect(fp)
    if w == 0 or h == 0:
        return out
    # on the footprint's box, padded with zeros by more than the closing reaches (also beyond the view's
    # border, so that the dilation does not clip there): the closing and the filling are the whole view's
    pad = k + 1
    big = cv2.copyMakeBorder(fp[v:v + h, u:u + w], pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    filled = fill_holes(cv2.morphologyEx(big, cv2.MORPH_CLOSE, se))
    r0, c0 = max(v - pad, 0), max(u - pad, 0)
    r1, c1 = min(v + h + pad, fp.shape[0]), min(u + w + pad, fp.shape[1])
    out[r0:r1, c0:c1] = filled[r0 - (v - pad):r1 - (v - pad), c0 - (u - pad):c1 - (u - pad)]
    return out


def _blur_reach(sigma: float) -> int:
    """Radius (px) of the kernel :func:`cv2.GaussianBlur` uses for a float image at ``sigma`` (size ``round(8 sigma + 1) | 1``)."""
    return (int(round(8.0 * sigma + 1.0)) | 1) // 2


def _window_box(mask: np.ndarray, reach: int) -> tuple[slice, slice] | None:
    """``mask``'s bounding box grown by ``reach`` px, within the image; ``None`` when empty.

    A blur of the box then gives the whole image's values on ``mask`` bit for bit, except when
    the box ends at the image's right border: OpenCV filters a row's last pixels on another
    path, so such a box takes whole rows.
    """
    u, v, w, h = cv2.boundingRect(np.ascontiguousarray(mask).view(np.uint8))
    if w == 0 or h == 0:
        return None
    H, W = mask.shape
    c0, c1 = max(u - reach, 0), min(u + w + reach, W)
    if c1 == W:
        c0 = 0
    return slice(max(v - reach, 0), min(v + h + reach, H)), slice(c0, c1)


def past_share(surface: np.ndarray, footprint: np.ndarray, z: float, z_before: float,
               maps: tuple[np.ndarray, np.ndarray], topview: TopView, previous: np.ndarray,
               noise: float, min_snr: float = 1.0, window_px: float = 3.0) -> np.ndarray:
    """Per pixel of the new layer's top, the share of its window's previous texture energy that lay past the part.

    Parameters are those of :func:`seen_past`.

    Returns
    -------
    ndarray, float32, shape (h, w)
        The share (0-1) where the band past the part brings the window more than ``(1 + min_snr)
        noise`` of texture energy; -1 elsewhere (off ``surface``, too little energy, the part did not
        rise or nothing lay past it).
    """
    out = np.full(surface.shape, -1.0, np.float32)
    if z_before >= z or not surface.any():
        return out
    sig = float(window_px)
    # only the windows of the surface's pixels are read: the band and both blurs on the surface's box,
    # grown by the blur's reach (the band by EDGE_PX more, which its dilation reads)
    box = _window_box(np.asarray(surface, bool), _blur_reach(sig))
    assert box is not None
    h, w = surface.shape
    outer = (slice(max(box[0].start - EDGE_PX, 0), min(box[0].stop + EDGE_PX, h)),
             slice(max(box[1].start - EDGE_PX, 0), min(box[1].stop + EDGE_PX, w)))
    inner = (slice(box[0].start - outer[0].start, box[0].stop - outer[0].start),
             slice(box[1].start - outer[1].start, box[1].stop - outer[1].start))
    outer_maps = (maps[0][:, outer[0], outer[1]], maps[1][:, outer[0], outer[1]])
    outline = outline_of(footprint, topview).astype(np.uint8)

    grow = np.ones((2 * EDGE_PX + 1, 2 * EDGE_PX + 1), np.uint8)

    def outside(zp: float) -> np.ndarray:
        mx, my = top_coords(outer_maps, zp)
        seen = cv2.remap(outline, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return (cv2.dilate(seen, grow) == 0)[inner]

    # past the part: the ray misses the outer outline at the previous top and on the bed (the
    # part's own faces and holes are not past it), off the high-pass spread of the part's edges
    band = outside(float(z_before)) & outside(0.0)
    if not band.any():
        return out
    e = np.asarray(previous, np.float32)[box] ** 2
    hidden = cv2.GaussianBlur(np.where(band, e, 0).astype(np.float32), (0, 0), sig)
    total = cv2.GaussianBlur(e, (0, 0), sig)
    valid = np.asarray(surface, bool)[box] & (hidden >= (1.0 + min_snr) * noise)
    crop = out[box]
    crop[valid] = hidden[valid] / (total[valid] + 1e-6)
    return out


def seen_past(surface: np.ndarray, footprint: np.ndarray, z: float, z_before: float,
              maps: tuple[np.ndarray, np.ndarray], topview: TopView, previous: np.ndarray,
              noise: float, min_snr: float = 1.0, window_px: float = 3.0,
              share: float = BLIND_SHARE) -> np.ndarray:
    """Pixels of the new layer's top whose window, in the previous photo, held mostly what lay past the part.

    Parameters
    ----------
    surface : ndarray, bool, shape (h, w)
        The new layer's footprint on its plane ``z``, seen through the camera (working image).
    footprint : ndarray, bool, shape (H, W)
        The new layer's top-view footprint (``topview`` geometry).
    z, z_before : float
        Height of the new layer's top and of the previous photo's top, mm.
    maps : (A, B)
        :func:`~layerwatch.analysis.scene_change.plane_maps` of the working image.
    topview : TopView
    previous : ndarray, float32, shape (h, w)
        High-passed texture of the previous photo (working image).
    noise : float
        Noise variance of the pair, grey levels^2 (the texture test's calibration).
    min_snr : float
        The band must bring ``(1 + min_snr) noise`` of texture energy to a window, the texture
        test's own floor (the sensor noise of a plain bed behind the part does not).
    window_px : float
        The comparison's window sigma, working px.
    share : float
        A pixel is blind when at least this share of its window's texture energy in the previous
        photo lay past the part (:data:`BLIND_SHARE`).

    Returns
    -------
    ndarray, bool, shape (h, w)
        Pixels of ``surface`` not to judge; empty when the part did not rise or nothing was hidden.
    """
    return past_share(surface, footprint, z, z_before, maps, topview, previous, noise, min_snr, window_px) >= share
