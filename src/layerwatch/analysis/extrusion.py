"""Nothing extruded ("air printing": a clog, a filament run-out), seen from photo to photo.

When the nozzle stops extruding, the printer goes on moving: the G-code adds
a layer, the photo shows the same part as before. A stationary camera sees
that directly: on the layer's top surface (its footprint, eroded by
``margin_mm``, projected into the image on the layer's plane through the
calibrated camera, :func:`~layerwatch.analysis.scene_change.predicted_change`)
the fine texture of the new beads replaces the old one after every printed
layer, and stays the same when nothing was extruded.

The texture is compared per block with the **zero-mean normalised
cross-correlation** (NCC) of the high-passed grey images (a Gaussian of
``HIGHPASS_SIGMA`` px removed): a change of light multiplies a block by a
smooth gain, which the high pass and the normalisation remove, so NCC stays
near 1 for an unchanged surface under new light and noise; new beads give
an unrelated texture (NCC near 0 for infill that turns, up to about 0.8 for
perimeters laid on their twins). The beads must be resolved: the comparison
runs on the photo at its own resolution (``[extrusion] working_px``). The layer's evidence is the **median block NCC**
against the photo two layers back (two layers of growth also shift the
surface by their height's parallax), and the check flags the layer when it
is above ``min_similarity``: two layers in a row added nothing, which is the
failure caught within two layers of its onset. A layer too small to judge on
its own is judged with the layer before it (both top surfaces against that
photo; :class:`~layerwatch.pipeline.checks.JobChecks`).

A faint top surface (a fine solid skin, low contrast) stays below that
similarity when nothing was extruded: sensor noise, independent from photo to
photo, and the blur change between the frames take its finest texture apart.
Lowering the threshold (or taking the noise out) lifts the clean layers that
look alike for real just as much: two layers up, the slicer lays the same
infill direction and perimeters on their twins. What tells them apart is
**height**: two printed layers raise the surface by their height, and a
stationary camera that looks at the print from the side sees its texture move
by that height's parallax (:func:`rise_parallax_px`; 2-3 px at the simulator's
45 degrees and 0.2-0.3 mm layers), a twin included; a surface on which nothing
was extruded stays in place. :func:`still_share` counts the blocks whose
texture fits the earlier photo better in place than shifted by the parallax.

References
----------
Lewis (1995), "Fast normalized cross-correlation" (zero-mean NCC).
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.analysis.block_moments import block_moments
from layerwatch.analysis.scene_change import channel_mean, working_crop

__all__ = ["HIGHPASS_SIGMA", "MIN_PARALLAX_PX", "block_ncc", "box_texture", "highpass", "rise_parallax_px", "shifted",
           "still_share"]

#: Gaussian (working px) removed from the grey image before the NCC: the shading, not the bead texture
HIGHPASS_SIGMA = 2.0
#: blocks whose high-passed texture is flatter than this (grey levels, in both photos) say nothing
MIN_TEXTURE = 0.5


def highpass(image: np.ndarray) -> np.ndarray:
    """Grey image minus its Gaussian blur (:data:`HIGHPASS_SIGMA`): float32 (h, w) from a (h, w, 3) working image."""
    g = channel_mean(np.asarray(image, np.float32)) if np.ndim(image) == 3 else np.asarray(image, np.float32)
    return g - cv2.GaussianBlur(g, (0, 0), HIGHPASS_SIGMA)


#: working px beyond a box that its texture depends on: the radii of to_working's blur (sigma 0.7: 3 px) and of
#: the high pass (sigma 2: 8 px), plus one
BLUR_REACH_PX = 12


def box_texture(photo: np.ndarray, size: tuple[int, int], box: tuple[slice, slice]) -> np.ndarray:
    """``highpass(to_working(photo, size))[box]``, resizing and blurring only the box and the blurs' reach.

    :func:`~layerwatch.analysis.scene_change.working_crop` (its ``photo``, ``size`` and ``box``) with
    :data:`BLUR_REACH_PX`: the frame is cut at the box grown by the reach of both blurs and aligned to
    whole source pixels, so the result is the whole-image computation's, bit for bit (tested).

    Returns
    -------
    ndarray, float32, shape (rows, cols)
    """
    work, (y0, x0) = working_crop(photo, size, box, BLUR_REACH_PX)
    grey = highpass(work)
    W, H = size
    (r0, r1), (c0, c1) = ((s.start or 0, n if s.stop is None else s.stop) for s, n in zip(box, (H, W), strict=True))
    return grey[r0 - y0:r1 - y0, c0 - x0:c1 - x0]


def block_ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray, block_px: int,
              min_share: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean normalised cross-correlation of two images per block, over the masked pixels.

    Parameters
    ----------
    a, b : ndarray, float32, shape (h, w)
        High-passed images (:func:`highpass`).
    mask : ndarray, bool, shape (h, w)
        Pixels compared.
    block_px : int
        Block side, px.
    min_share : float
        Share of a block that must be masked for it to be scored.

    Returns
    -------
    ncc : ndarray, float32, shape (h // block_px, w // block_px)
        In [-1, 1] (0 where undefined).
    scored : ndarray, bool, same shape
        Blocks at least ``min_share`` masked with texture above :data:`MIN_TEXTURE` in either image.
    """
    h, w = mask.shape
    n, m = h // block_px, w // block_px
    k = np.ascontiguousarray(mask[:n * block_px, :m * block_px]).astype(np.float32)
    frac = cv2.resize(k, (m, n), interpolation=cv2.INTER_AREA)
    f = np.maximum(frac, 1e-6)
    sx, sy, sxx, syy, sxy = block_moments(a, b, block_px, mask.astype(np.float32))  # each mean(v * k), one pass
    mx, my = sx / f, sy / f
    vx, vy = np.maximum(sxx / f - mx * mx, 0), np.maximum(syy / f - my * my, 0)
    cov = sxy / f - mx * my
    ncc = np.where(vx * vy > 0, cov / np.sqrt(np.maximum(vx * vy, 1e-12)), 0.0).astype(np.float32)
    texture = np.sqrt(np.maximum(vx, vy))
    return np.clip(ncc, -1, 1), (frac >= min_share) & (texture > MIN_TEXTURE)


#: a parallax of the two layers' height shorter than this (working px: a camera looking straight down) cannot
#: tell a raised surface from one that stayed
MIN_PARALLAX_PX = 1.0


def rise_parallax_px(camera, xy_mm: tuple[float, float], z_mm: float, dz_mm: float, scale: float = 1.0) -> np.ndarray:
    """Image displacement of a bed point raised from ``z_mm - dz_mm`` to ``z_mm``, px.

    The camera model's projection of the two points (lens distortion included).
    :func:`layerwatch.analysis.layer_change.parallax_px` estimates a shift of the
    opposite sign from the plane maps' medians over the print's box; on the 12 mm
    cube's small box that estimate has a sideways component of 0.67 px that the
    projection does not (0.4 mm: (0.67, 1.93) against (0, 1.99) px), so the
    nothing-extruded check projects.

    Parameters
    ----------
    camera : CameraModel
        Posed camera (its image size).
    xy_mm : (float, float)
        Bed position, mm.
    z_mm, dz_mm : float
        Height and the rise, mm.
    scale : float
        Working px per camera px.

    Returns
    -------
    ndarray, float64, shape (2,)
        ``(dx, dy)``, working px.
    """
    rvec, tvec = camera.pose
    pts = np.array([[xy_mm[0], xy_mm[1], z_mm - dz_mm], [xy_mm[0], xy_mm[1], z_mm]], np.float64)
    uv = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, tvec, camera.K, camera.dist)[0].reshape(2, 2)
    return (uv[1] - uv[0]) * float(scale)


def shifted(image: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``image`` moved by ``d = (dx, dy)`` px (bilinear; edges reflected): ``out(p + d) = image(p)``."""
    M = np.array([[1, 0, d[0]], [0, 1, d[1]]], np.float32)
    h, w = image.shape
    return cv2.warpAffine(np.asarray(image, np.float32), M, (w, h), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)


def still_share(a: np.ndarray, b: np.ndarray, mask: np.ndarray, block_px: int, d: np.ndarray,
                scored: np.ndarray, min_share: float = 0.5, in_place: np.ndarray | None = None) -> float:
    """Share of the ``scored`` blocks whose texture in ``a`` fits ``b`` better in place than moved by ``d``.

    ``b`` is the earlier photo, ``d`` the parallax the surface's rise between the photos would
    give (:func:`rise_parallax_px`): near 1 when the surface stayed where it was (nothing
    extruded), low when it rose (a new layer, even one that looks like the old: its texture
    fits the moved photo better).

    Parameters
    ----------
    a, b : ndarray, float32, shape (h, w)
        High-passed photos (:func:`highpass`), ``b`` the earlier.
    mask : ndarray, bool, shape (h, w)
        The judged surface.
    block_px : int
        Block side, px.
    d : ndarray, shape (2,)
        Parallax, px.
    scored : ndarray, bool, shape (h // block_px, w // block_px)
        The blocks judged (:func:`block_ncc` of ``a`` and ``b``).
    min_share : float
        As for :func:`block_ncc`.
    in_place : ndarray, float32, shape of ``scored``, optional
        :func:`block_ncc` of ``a`` and ``b`` where the caller has it (computed otherwise).

    Returns
    -------
    float
        In [0, 1] (nan when no block is scored).
    """
    if not scored.any():
        return float("nan")
    if in_place is None:
        in_place, _ = block_ncc(a, b, mask, block_px, min_share)
    moved, _ = block_ncc(a, shifted(b, d), mask, block_px, min_share)
    return float(np.mean(in_place[scored] > moved[scored]))
