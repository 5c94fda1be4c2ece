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
failure caught within two layers of its onset.

References
----------
Lewis (1995), "Fast normalized cross-correlation" (zero-mean NCC).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from layerwatch.analysis.scene_change import channel_mean

__all__ = ["HIGHPASS_SIGMA", "ExtrusionEvidence", "block_ncc", "highpass", "surface_similarity"]

#: Gaussian (working px) removed from the grey image before the NCC: the shading, not the bead texture
HIGHPASS_SIGMA = 2.0
#: blocks whose high-passed texture is flatter than this (grey levels, in both photos) say nothing
MIN_TEXTURE = 0.5


def highpass(image: np.ndarray) -> np.ndarray:
    """Grey image minus its Gaussian blur (:data:`HIGHPASS_SIGMA`): float32 (h, w) from a (h, w, 3) working image."""
    g = channel_mean(np.asarray(image, np.float32)) if np.ndim(image) == 3 else np.asarray(image, np.float32)
    return g - cv2.GaussianBlur(g, (0, 0), HIGHPASS_SIGMA)


def block_ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray, block_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean normalised cross-correlation of two images per block, over the masked pixels.

    Parameters
    ----------
    a, b : ndarray, float32, shape (h, w)
        High-passed images (:func:`highpass`).
    mask : ndarray, bool, shape (h, w)
        Pixels compared.
    block_px : int
        Block side, px.

    Returns
    -------
    ncc : ndarray, float32, shape (h // block_px, w // block_px)
        In [-1, 1] (0 where undefined).
    scored : ndarray, bool, same shape
        Blocks at least half masked with texture above :data:`MIN_TEXTURE` in either image.
    """
    h, w = mask.shape
    n, m = h // block_px, w // block_px
    crop = (slice(0, n * block_px), slice(0, m * block_px))
    k = np.ascontiguousarray(mask[crop]).astype(np.float32)
    x, y = np.ascontiguousarray(a[crop]), np.ascontiguousarray(b[crop])

    def mean(v: np.ndarray) -> np.ndarray:
        return cv2.resize(v * k, (m, n), interpolation=cv2.INTER_AREA)

    frac = cv2.resize(k, (m, n), interpolation=cv2.INTER_AREA)
    f = np.maximum(frac, 1e-6)
    mx, my = mean(x) / f, mean(y) / f
    vx, vy = np.maximum(mean(x * x) / f - mx * mx, 0), np.maximum(mean(y * y) / f - my * my, 0)
    cov = mean(x * y) / f - mx * my
    ncc = np.where(vx * vy > 0, cov / np.sqrt(np.maximum(vx * vy, 1e-12)), 0.0).astype(np.float32)
    texture = np.sqrt(np.maximum(vx, vy))
    return np.clip(ncc, -1, 1), (frac >= 0.5) & (texture > MIN_TEXTURE)


@dataclass(frozen=True)
class ExtrusionEvidence:
    """How much a layer's top surface looks like the earlier photos.

    Attributes
    ----------
    similarity : float
        Median block NCC of the surface against the previous photo and the one
        before it, the smaller of the two (``nan`` when not judged).
    blocks : int
        Blocks compared.
    area_mm2 : float
        The top surface judged, mm^2 (bed plane).
    """

    similarity: float
    blocks: int
    area_mm2: float


def surface_similarity(current: np.ndarray, earlier: list[np.ndarray], surface: np.ndarray,
                       block_px: int) -> tuple[float, int]:
    """The smallest median block NCC of ``current`` against each of the ``earlier`` photos on ``surface``.

    Parameters
    ----------
    current : ndarray, float32, shape (h, w)
        High-passed working image of this layer's photo (:func:`highpass`).
    earlier : list of ndarray
        High-passed working images of the previous photos (newest first).
    surface : ndarray, bool, shape (h, w)
        The layer's top surface in the working image.
    block_px : int

    Returns
    -------
    similarity : float
        ``nan`` when no block is compared.
    blocks : int
        Blocks compared (against the newest earlier photo).
    """
    sims, blocks = [], 0
    for k, prev in enumerate(earlier):
        ncc, scored = block_ncc(current, prev, surface, block_px)
        if not scored.any():
            return float("nan"), 0
        if k == 0:
            blocks = int(scored.sum())
        sims.append(float(np.median(ncc[scored])))
    return (min(sims) if sims else float("nan")), blocks
