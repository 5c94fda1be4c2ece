"""Histogram-of-oriented-gradients block descriptors, vectorised.

The photo's top view and the rendered reference are each turned into a
tensor of normalised HOG blocks, shape ``(N, M, k)`` with
``k = block_cells**2 * bins`` (36 for the paper's 8-px cells, 2x2 blocks and
9 unsigned orientation bins over 0-180 degrees).

The numbers reproduce :func:`skimage.feature.hog` (``feature_vector=False``,
reshaped to ``(N, M, k)``) to better than 1e-6, including its details:

* gradients are central differences ``I[r+1] - I[r-1]`` with the first and
  last row/column set to zero (no ``np.gradient`` one-sided borders);
* orientation ``= rad2deg(arctan2(g_row, g_col)) % 180``; each pixel votes
  its full magnitude into exactly one bin ``[edge_i, edge_{i+1})`` (no
  interpolation between bins or cells), the edges being single-precision
  multiples of ``180 / bins`` as in skimage's Cython kernel;
* a cell's bin value is the vote sum accumulated in single precision (as
  skimage does) divided by the cell's pixel count;
* only whole cells are used (``H // cell_px`` rows of cells), blocks slide
  by one cell, and block normalisation uses ``eps = 1e-5`` exactly as
  skimage's ``L1``, ``L1-sqrt``, ``L2`` and ``L2-Hys`` (clip at 0.2).

**Votes on the 0/180-degree bin edge** (``votes``; ``"one_bin"`` is
skimage's and the paper's). An edge along the image's columns has its
gradient at 0 degrees, which is the edge between the first and the last
bin (0 and 180 degrees are one orientation). A rendered reference draws
such an edge perfectly straight: every one of its gradients has
``g_row == 0`` exactly and votes into the first bin. The photo's same edge
is tilted by a fraction of a degree to a few degrees (bead wobble, the
perspective of a wall's top edge, calibration residuals) and votes into
the first bin, the last, or both; on clean layers of the window part two
images of one wall shared nothing (cosine 0.25, all of the photo's votes in
the last bin at 177-178 degrees). Edges along the rows (90 degrees) sit
mid-bin and were never at risk.

* ``"split_ties"``: a vote lying exactly on that edge (``g_row == 0``,
  ``g_col != 0``) goes half into the first and half into the last bin, the
  expected vote of an edge whose direction spreads symmetrically round 0
  degrees. It only changes gradients at exactly 0 degrees (in practice: a
  rendered image's straight edges; no other bin edge is hit exactly, their
  slopes being irrational); every other vote is skimage's.
* ``"interpolated"``: every vote is split linearly between the two bins
  whose centres ``(i + 0.5) * 180 / bins`` enclose its orientation,
  circularly (Dalal & Triggs 2005, Section 6.3). Continuous in orientation,
  but it also blurs the small turns an infill or thin-wall defect makes
  (measured: ``docs/evaluation/single_photo.md``).

Colour images (``(H, W, C)``) follow skimage's ``channel_axis=-1`` rule: per
pixel, the gradient of the channel with the largest gradient magnitude is
used. That rule does not depend on channel order, so BGR (OpenCV) and RGB
input give identical descriptors.

Block geometry: block ``(i, j)`` covers pixel rows
``[i*cell_px, i*cell_px + block_cells*cell_px)`` and the same columns.

Speed: one fused Numba pass per image builds the cell histograms. For uint8
images the gradients are integers in [-255, 255], so the bin of every
possible gradient is tabulated once with numpy's own ``arctan2``/``rad2deg``/
``% 180`` (identical to skimage's arithmetic); other dtypes fold the gradient
into the upper half plane and compare it with each bin edge by the sign of a
cross product, falling back to skimage's degree arithmetic within 1e-9 rad
of an edge. float32 images are differenced in float64 (skimage subtracts in
float32), a difference far below 1e-6 after normalisation.

References
----------
Petsiuk & Pearce (2022), Section 2.4 (HOG, 8-px cells, 2x2 blocks, 9 bins);
Dalal & Triggs (2005), "Histograms of Oriented Gradients for Human Detection".
"""

from __future__ import annotations

import numpy as np

from layerwatch.analysis.hog_kernels import (
    hist_from_gradients,
    hist_from_image,
    hist_from_u8,
    hist_soft_from_gradients,
    hist_soft_from_image,
    normalize_kernel,
    zero_angle_votes,
)
from layerwatch.errors import AnalysisError

__all__ = ["hog_blocks", "BLOCK_NORMS", "VOTES", "block_energy", "hog_cell_histograms", "gradients", "normalize_blocks"]

BLOCK_NORMS = ("L2-Hys", "L2", "L1", "L1-sqrt")
#: how a gradient votes: into its one bin (skimage), split when it lies exactly on the 0/180 bin edge, or
#: interpolated between the two nearest bin centres (module notes)
VOTES = ("one_bin", "split_ties", "interpolated")


def gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradients with zeroed borders (skimage's convention).

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, C)
        Intensities (any real dtype; computed in float64).

    Returns
    -------
    g_row, g_col : ndarray, shape (H, W), float64
        ``I[r+1, c] - I[r-1, c]`` and ``I[r, c+1] - I[r, c-1]``; zero on the
        first/last row (``g_row``) and column (``g_col``). For colour input,
        per pixel the channel with the largest ``hypot(g_row, g_col)`` wins
        (first channel on ties, like ``argmax``).
    """
    img = np.asarray(image, dtype=np.float64)
    g_row = np.empty(img.shape, dtype=np.float64)
    g_col = np.empty(img.shape, dtype=np.float64)
    g_row[[0, -1]] = 0.0
    g_col[:, [0, -1]] = 0.0
    np.subtract(img[2:], img[:-2], out=g_row[1:-1])
    np.subtract(img[:, 2:], img[:, :-2], out=g_col[:, 1:-1])
    if img.ndim == 3:
        mag = np.hypot(g_row, g_col)
        best = mag.argmax(axis=2)[..., None]
        g_row = np.take_along_axis(g_row, best, axis=2)[..., 0]
        g_col = np.take_along_axis(g_col, best, axis=2)[..., 0]
    return g_row, g_col


def _bin_edges(bins: int) -> np.ndarray:
    """Bin edges in degrees, float64 values of skimage's float32 arithmetic."""
    width = np.float32(180.0 / bins)
    return np.array([np.float32(width * np.float32(i)) for i in range(bins + 1)], dtype=np.float64)


_U8_LUTS: dict[int, np.ndarray] = {}


def _u8_bin_table(bins: int) -> np.ndarray:
    """Bin of every integer gradient (g_row, g_col) in [-255, 255]^2, -1 for none.

    Computed with skimage's own arithmetic (numpy ``arctan2``, ``rad2deg``,
    ``% 180``, float32 edges), so uint8 images bin exactly as in skimage.
    """
    if bins not in _U8_LUTS:
        g = np.arange(-255, 256, dtype=np.float64)
        ang = np.rad2deg(np.arctan2(g[:, None], g[None, :])) % 180
        edges = _bin_edges(bins)
        b = np.searchsorted(edges, ang, side="right") - 1
        b[(b < 0) | (b >= bins)] = -1
        _U8_LUTS[bins] = b.astype(np.int8 if bins < 127 else np.int16)
    return _U8_LUTS[bins]


def hog_cell_histograms(image: np.ndarray, cell_px: int = 8, bins: int = 9, gamma: bool = False,
                        votes: str = "one_bin") -> np.ndarray:
    """Per-cell orientation histograms before block normalisation.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, C)
        Intensities, finite.
    cell_px : int
        Cell side in pixels.
    bins : int
        Unsigned orientation bins over [0, 180) degrees.
    gamma : bool
        Take ``sqrt`` of the intensities first (skimage ``transform_sqrt``).
    votes : {"one_bin", "split_ties", "interpolated"}
        How a gradient votes (module notes); ``"one_bin"`` is skimage's.

    Returns
    -------
    ndarray, shape (H // cell_px, W // cell_px, bins), float64
        Mean gradient magnitude per pixel voting into each bin (intensity
        units per pixel, central differences span 2 px).
    """
    img = _check_image(image)
    if gamma:
        if np.any(img < 0):
            raise AnalysisError("gamma=True needs non-negative intensities; pass gamma=False.")
        img = np.sqrt(img.astype(np.float64))
    n_cr, n_cc = img.shape[0] // cell_px, img.shape[1] // cell_px
    edges = _bin_edges(bins)
    rad = np.deg2rad(edges)
    cos_e, sin_e = np.cos(rad), np.sin(rad)
    out = np.zeros((n_cr, n_cc, bins), dtype=np.float64)
    if votes not in VOTES:
        raise AnalysisError(f"unknown vote rule {votes!r}; use one of {', '.join(VOTES)}.")
    if votes == "interpolated":
        centres = np.deg2rad((np.arange(bins) + 0.5) * (180.0 / bins))
        cos_c, sin_c = np.cos(centres), np.sin(centres)
        if img.ndim == 2:
            hist_soft_from_image(img if img.dtype != np.uint8 else img.astype(np.float32), int(cell_px),
                                 n_cr, n_cc, cos_c, sin_c, out)
        else:
            g_row, g_col = gradients(img)
            hist_soft_from_gradients(g_row, g_col, int(cell_px), n_cr, n_cc, cos_c, sin_c, out)
        return out
    half = np.zeros((n_cr, n_cc), np.float64) if votes == "split_ties" else None
    if img.dtype == np.uint8:
        hist_from_u8(img, int(cell_px), n_cr, n_cc, _u8_bin_table(bins), bins, out)
    elif img.ndim == 2:  # (the ties' votes in the same pass: they read the same gradients)
        hist_from_image(img, int(cell_px), n_cr, n_cc, cos_e, sin_e, edges, out, half)
    else:
        g_row, g_col = gradients(img)
        hist_from_gradients(g_row, g_col, int(cell_px), n_cr, n_cc, cos_e, sin_e, edges, out)
    if half is not None:
        if img.dtype == np.uint8:
            zero_angle_votes(img, int(cell_px), n_cr, n_cc, half)
        elif img.ndim == 3:  # the colour image's gradients, computed above
            on = (g_row == 0.0)[: n_cr * cell_px, : n_cc * cell_px]
            g = np.where(on, np.abs(g_col[: n_cr * cell_px, : n_cc * cell_px]), 0.0)
            half = g.reshape(n_cr, cell_px, n_cc, cell_px).sum(axis=(1, 3)) / (cell_px * cell_px)
        half *= 0.5
        out[..., 0] = np.maximum(out[..., 0] - half, 0.0)  # (the first bin's votes were summed in float32)
        out[..., bins - 1] += half
    return out


def _check_image(image: np.ndarray) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (1, 2, 3, 4)):
        raise AnalysisError(
            f"HOG needs a (H, W) grey or (H, W, C) colour image, got shape {arr.shape}."
        )
    if arr.dtype.kind not in "uif":
        raise AnalysisError(f"HOG needs a numeric image, got dtype {arr.dtype}; convert to uint8 or float.")
    img = arr[..., 0] if arr.ndim == 3 and arr.shape[2] == 1 else arr
    # grey uint8/uint16/float32/float64 go to the kernel as they are (it
    # subtracts in float64); colour and other integer types become float64
    if img.ndim == 3 or img.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        img = img.astype(np.float64)
    img = np.ascontiguousarray(img)
    if img.dtype.kind == "f" and not np.all(np.isfinite(img)):
        raise AnalysisError("image contains NaN or infinite values; replace them before the analysis.")
    return img


def normalize_blocks(hist: np.ndarray, block_cells: int = 2, block_norm: str = "L2-Hys") -> np.ndarray:
    """Group cell histograms into overlapping blocks and normalise each.

    Parameters
    ----------
    hist : ndarray, shape (R, C, bins)
        Cell histograms from :func:`hog_cell_histograms`.
    block_cells : int
        Block side in cells; blocks slide by one cell.
    block_norm : {"L2-Hys", "L2", "L1", "L1-sqrt"}
        skimage's normalisations with ``eps = 1e-5``.

    Returns
    -------
    ndarray, shape (R - block_cells + 1, C - block_cells + 1, block_cells**2 * bins), float64
        Bin order inside a block: cell row, cell column, orientation.
    """
    if block_norm not in BLOCK_NORMS:
        raise AnalysisError(f"unknown block_norm {block_norm!r}; use one of {', '.join(BLOCK_NORMS)}.")
    b = int(block_cells)
    n = hist.shape[0] - b + 1
    m = hist.shape[1] - b + 1
    out = np.empty((n, m, b * b * hist.shape[2]), dtype=np.float64)
    normalize_kernel(np.ascontiguousarray(hist, dtype=np.float64), b, BLOCK_NORMS.index(block_norm), out)
    return out


def hog_blocks(
    image: np.ndarray,
    cell_px: int = 8,
    block_cells: int = 2,
    bins: int = 9,
    block_norm: str = "L2-Hys",
    gamma: bool = False,
    *,
    return_energy: bool = False,
    votes: str = "one_bin",
):
    """Normalised HOG block tensor of one image (skimage-exact).

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, C)
        Grey or colour intensities (uint8, uint16 or float; NaN rejected).
        Colour uses skimage's per-pixel dominant-channel gradient.
    cell_px : int
        Cell side in pixels (paper: 8).
    block_cells : int
        Block side in cells (paper: 2).
    bins : int
        Orientation bins over 0-180 degrees (paper: 9).
    block_norm : {"L2-Hys", "L2", "L1", "L1-sqrt"}
        Block normalisation (paper: L2-Hys).
    gamma : bool
        Square-root gamma compression first (skimage ``transform_sqrt``).
    return_energy : bool
        Also return each block's mean gradient magnitude before normalisation.
    votes : {"one_bin", "split_ties", "interpolated"}
        How a gradient votes (:func:`hog_cell_histograms`); ``"one_bin"`` is skimage's.

    Returns
    -------
    blocks : ndarray, shape (N, M, k), float64
        ``N = H // cell_px - block_cells + 1`` (likewise ``M``),
        ``k = block_cells**2 * bins``; every block is non-negative with
        Euclidean norm <= 1 for every normalisation.
    energy : ndarray, shape (N, M), float64, only if ``return_energy``
        Mean gradient magnitude per pixel over the block's pixels, in
        intensity units (sum of the block's cell histograms / block_cells**2).

    Raises
    ------
    AnalysisError
        Bad shape/dtype, NaN, unknown norm, or an image smaller than one block.

    References
    ----------
    Petsiuk & Pearce (2022), Section 2.4; skimage.feature.hog.
    """
    if int(cell_px) < 1 or int(block_cells) < 1 or int(bins) < 1:
        raise AnalysisError("cell_px, block_cells and bins must all be >= 1.")
    img = _check_image(image)
    if img.shape[0] // cell_px < block_cells or img.shape[1] // cell_px < block_cells:
        raise AnalysisError(
            f"image {img.shape[0]}x{img.shape[1]} px is smaller than one HOG block of "
            f"{block_cells * cell_px} px; use a larger image or smaller cells."
        )
    hist = hog_cell_histograms(img, int(cell_px), int(bins), gamma, votes)
    blocks = normalize_blocks(hist, int(block_cells), block_norm)
    if not return_energy:
        return blocks
    return blocks, block_energy(hist, int(block_cells))


def block_energy(hist: np.ndarray, block_cells: int = 2) -> np.ndarray:
    """Mean gradient magnitude per pixel of every block, before normalisation.

    Parameters
    ----------
    hist : ndarray, shape (R, C, bins)
        Cell histograms from :func:`hog_cell_histograms`.
    block_cells : int
        Block side in cells.

    Returns
    -------
    ndarray, shape (R - block_cells + 1, C - block_cells + 1), float64
        Sum of the block's cell histograms / ``block_cells**2`` (intensity units).
    """
    cell_energy = hist.sum(axis=2)
    b = int(block_cells)
    n, m = hist.shape[0] - b + 1, hist.shape[1] - b + 1
    energy = np.zeros((n, m), dtype=np.float64)
    for di in range(b):
        for dj in range(b):
            energy += cell_energy[di : di + n, dj : dj + m]
    return energy / (b * b)
