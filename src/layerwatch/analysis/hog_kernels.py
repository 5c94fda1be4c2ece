"""Numba inner loops of the HOG descriptor (see :mod:`layerwatch.analysis.hog`).

Each histogram kernel accumulates a cell's votes in single precision in
skimage's pixel order (rows, then columns) and divides by the cell area, as
skimage's Cython ``cell_hog`` does; ``out`` is (rows of cells, cells, bins).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["hist_from_image", "hist_from_u8", "hist_from_gradients", "hist_soft_from_image", "hist_soft_from_gradients",
           "normalize_kernel", "zero_angle_votes"]


@njit(cache=True, nogil=True, inline="always")
def _bin_of(gr, gc, mag, cos_e, sin_e, edges):  # pragma: no cover - jit
    """Orientation bin of one gradient as skimage assigns it, or -1 (no bin).

    skimage bins ``rad2deg(arctan2(gr, gc)) % 180`` against the edges. We fold
    the gradient into the upper half plane and count the edges ``e`` with
    ``angle >= e`` through the sign of ``sin(angle - e)``; only when a
    gradient lies within 1e-9 rad of an edge do we fall back to skimage's
    degree arithmetic (libm atan2), which decides ties exactly as it does.
    """
    bins = edges.size - 1
    fr, fc = gr, gc
    if fr < 0.0 or (fr == 0.0 and fc < 0.0):
        fr = -fr
        fc = -fc
    # an edge at 180 degrees bounds nothing: folded angles are < 180
    last = bins if edges[bins] < 180.0 else bins - 1
    b = 0
    close = False
    for i in range(1, last + 1):
        t = fr * cos_e[i] - fc * sin_e[i]
        if t >= 0.0:
            b += 1
        if abs(t) <= 1e-9 * mag:
            close = True
    if close:
        b = _bin_by_angle(gr, gc, edges)
    # b == bins: at or above the last (float32) edge, outside every bin
    return b if b < bins else -1


@njit(cache=True, nogil=True, inline="always")
def _bin_by_angle(gr, gc, edges):  # pragma: no cover - jit
    """skimage's bin of a gradient within 1e-9 rad of an edge: its degree arithmetic (libm atan2, ``% 180``);
    ``edges.size - 1`` (no bin) at or above the last edge."""
    bins = edges.size - 1
    ang = math.atan2(gr, gc) * (180.0 / np.pi)
    if ang >= 180.0:
        ang = 0.0
    elif ang < 0.0:
        ang += 180.0
    b = 0
    while b < bins and ang >= edges[b + 1]:
        b += 1
    return b


@njit(cache=True, nogil=True)
def hist_from_image(img, cell_px, n_cr, n_cc, cos_e, sin_e, edges, out, zero=None):  # pragma: no cover - jit
    """Gradient + binning + cell accumulation for a grey image of any real dtype, a row of pixels at a time.

    Each row's gradients, folded gradients and magnitudes are computed first, then the edge tests of
    :func:`_bin_of` edge after edge over the whole row (loops without branches that the compiler vectorises;
    the same products, differences and comparisons per pixel), then the votes in pixel order into one
    accumulator per cell of the cell row, which adds each cell's pixels in skimage's order (rows, then
    columns): the same float32 sums as a cell at a time. ``zero``: an (n_cr, n_cc) float64 array, or None:
    filled with :func:`zero_angle_votes` of the image, value for value (the same gradients, summed in the same
    order in float64), in the same pass.
    """
    h, w = img.shape
    bins = edges.size - 1
    last = bins if edges[bins] < 180.0 else bins - 1  # an edge at 180 degrees bounds nothing
    area = cell_px * cell_px
    width = n_cc * cell_px
    if width == 0:
        return
    acc = np.zeros((n_cc, bins), dtype=np.float32)
    flat = np.zeros(n_cc)  # each cell's votes at exactly 0 degrees (``zero``)
    grs, gcs = np.zeros(width), np.zeros(width)
    fr, fc, mag = np.empty(width), np.empty(width), np.empty(width)
    count, close = np.empty(width, np.int32), np.empty(width, np.int32)
    inner = min(width, w - 1)  # columns 1..inner-1 have both neighbours
    cell_of = np.empty(width, np.int64)  # each column's cell (no division per pixel)
    for c in range(width):
        cell_of[c] = c // cell_px
    for ci in range(n_cr):
        acc[:] = 0.0
        flat[:] = 0.0
        for r in range(ci * cell_px, ci * cell_px + cell_px):
            if 0 < r < h - 1:
                for c in range(width):
                    grs[c] = float(img[r + 1, c]) - float(img[r - 1, c])
            else:
                grs[:] = 0.0
            for c in range(1, inner):
                gcs[c] = float(img[r, c + 1]) - float(img[r, c - 1])
            gcs[0] = 0.0
            if inner < width:
                gcs[inner] = 0.0
            for c in range(width):  # folded into the upper half plane (_bin_of)
                gr, gc = grs[c], gcs[c]
                neg = (gr < 0.0) | ((gr == 0.0) & (gc < 0.0))
                fr[c] = -gr if neg else gr
                fc[c] = -gc if neg else gc
                mag[c] = math.sqrt(gr * gr + gc * gc)
                count[c] = 0
                close[c] = 0
            for i in range(1, last + 1):
                ce, se = cos_e[i], sin_e[i]
                for c in range(width):
                    t = fr[c] * ce - fc[c] * se
                    count[c] += t >= 0.0
                    close[c] |= abs(t) <= 1e-9 * mag[c]
            for c in range(width):
                gr, gc = grs[c], gcs[c]
                cj = cell_of[c]
                if gr == 0.0:
                    flat[cj] += abs(gc)
                    if gc == 0.0:
                        continue
                b = _bin_by_angle(gr, gc, edges) if close[c] else count[c]
                if b < bins:  # single-precision accumulation, as skimage's cell_hog
                    acc[cj, b] = np.float32(np.float64(acc[cj, b]) + mag[c])
        for cj in range(n_cc):
            for b in range(bins):
                out[ci, cj, b] = np.float32(np.float64(acc[cj, b]) / area)
            if zero is not None:
                zero[ci, cj] = flat[cj] / area


@njit(cache=True, nogil=True)
def hist_from_u8(img, cell_px, n_cr, n_cc, lut, bins, out):  # pragma: no cover - jit
    """uint8 fast path: integer gradients, bin looked up in a table made with numpy's arctan2.

    Rows are walked in image order with one accumulator per cell of the
    current cell row, which adds each cell's pixels in skimage's order.
    """
    h, w = img.shape
    area = cell_px * cell_px
    acc = np.zeros((n_cc, bins), dtype=np.float32)
    for ci in range(n_cr):
        acc[:] = 0.0
        for r in range(ci * cell_px, ci * cell_px + cell_px):
            row_in = 0 < r < h - 1
            for c in range(n_cc * cell_px):
                gr = np.int32(img[r + 1, c]) - np.int32(img[r - 1, c]) if row_in else np.int32(0)
                gc = np.int32(img[r, c + 1]) - np.int32(img[r, c - 1]) if 0 < c < w - 1 else np.int32(0)
                if gr == 0 and gc == 0:
                    continue
                b = lut[gr + 255, gc + 255]
                if b >= 0:
                    mag = math.sqrt(np.float64(gr * gr + gc * gc))
                    cj = c // cell_px
                    acc[cj, b] = np.float32(np.float64(acc[cj, b]) + mag)
        for cj in range(n_cc):
            for b in range(bins):
                out[ci, cj, b] = np.float32(np.float64(acc[cj, b]) / area)


@njit(cache=True, nogil=True)
def hist_from_gradients(g_row, g_col, cell_px, n_cr, n_cc, cos_e, sin_e, edges, out):  # pragma: no cover - jit
    bins = edges.size - 1
    area = cell_px * cell_px
    acc = np.zeros(bins, dtype=np.float32)
    for ci in range(n_cr):
        for cj in range(n_cc):
            acc[:] = 0.0
            for r in range(ci * cell_px, ci * cell_px + cell_px):
                for c in range(cj * cell_px, cj * cell_px + cell_px):
                    gr = g_row[r, c]
                    gc = g_col[r, c]
                    if gr == 0.0 and gc == 0.0:
                        continue
                    mag = math.sqrt(gr * gr + gc * gc)
                    b = _bin_of(gr, gc, mag, cos_e, sin_e, edges)
                    if b >= 0:
                        acc[b] = np.float32(np.float64(acc[b]) + mag)
            for b in range(bins):
                out[ci, cj, b] = np.float32(np.float64(acc[b]) / area)


@njit(cache=True, nogil=True, inline="always")
def _soft_vote(gr, gc, mag, cos_c, sin_c, acc):  # pragma: no cover - jit
    """Split one gradient's magnitude between the two bins whose centres enclose its orientation.

    Bin ``i`` is centred on ``c_i = (i + 0.5) * 180 / bins`` degrees
    (``cos_c``, ``sin_c``). The gradient is folded into the upper half plane
    (orientation ``theta`` in [0, 180)); the centres below and above it are
    found by the sign of ``sin(theta - c_i)`` (a cross product, no arctan),
    and the magnitude is split in proportion to the sines of the angular
    distances to the two centres (``sin(d0) / (sin(d0) + sin(d1))`` goes to
    the far one: linear interpolation to within 0.2 % of a vote for 9 bins).
    Orientation is circular: below the first centre and above the last, the
    first and the last bin share the vote (0 and 180 degrees are one line).
    """
    bins = cos_c.size
    if gr < 0.0 or (gr == 0.0 and gc < 0.0):
        gr = -gr
        gc = -gc
    k = 0
    for i in range(bins):
        k += (gr * cos_c[i] - gc * sin_c[i]) >= 0.0  # theta >= c_i (the centres are in increasing order)
    i0 = k - 1 if k > 0 else bins - 1
    i1 = k if k < bins else 0
    s0 = gr * cos_c[i0] - gc * sin_c[i0]  # sin(theta - c_i0) * mag
    s1 = gc * sin_c[i1] - gr * cos_c[i1]  # sin(c_i1 - theta) * mag
    if k == 0:  # below the first centre: the last one lies at c - 180
        s0 = -s0
    elif k == bins:  # above the last centre: the first one lies at c + 180
        s1 = -s1
    tot = s0 + s1
    w1 = mag * s0 / tot if tot > 0.0 else 0.5 * mag
    acc[i0] += mag - w1
    acc[i1] += w1


@njit(cache=True, nogil=True)
def hist_soft_from_image(img, cell_px, n_cr, n_cc, cos_c, sin_c, out):  # pragma: no cover - jit
    """Fused gradient + interpolated orientation binning (:func:`_soft_vote`) + cell accumulation, grey image."""
    h, w = img.shape
    area = cell_px * cell_px
    acc = np.zeros(cos_c.size, dtype=np.float64)
    for ci in range(n_cr):
        for cj in range(n_cc):
            acc[:] = 0.0
            for r in range(ci * cell_px, ci * cell_px + cell_px):
                row_in = 0 < r < h - 1
                for c in range(cj * cell_px, cj * cell_px + cell_px):
                    gr = float(img[r + 1, c]) - float(img[r - 1, c]) if row_in else 0.0
                    gc = float(img[r, c + 1]) - float(img[r, c - 1]) if 0 < c < w - 1 else 0.0
                    if gr == 0.0 and gc == 0.0:
                        continue
                    _soft_vote(gr, gc, math.sqrt(gr * gr + gc * gc), cos_c, sin_c, acc)
            for b in range(cos_c.size):
                out[ci, cj, b] = acc[b] / area


@njit(cache=True, nogil=True)
def hist_soft_from_gradients(g_row, g_col, cell_px, n_cr, n_cc, cos_c, sin_c, out):  # pragma: no cover - jit
    """:func:`hist_soft_from_image` on precomputed gradients (colour images)."""
    area = cell_px * cell_px
    acc = np.zeros(cos_c.size, dtype=np.float64)
    for ci in range(n_cr):
        for cj in range(n_cc):
            acc[:] = 0.0
            for r in range(ci * cell_px, ci * cell_px + cell_px):
                for c in range(cj * cell_px, cj * cell_px + cell_px):
                    gr = g_row[r, c]
                    gc = g_col[r, c]
                    if gr == 0.0 and gc == 0.0:
                        continue
                    _soft_vote(gr, gc, math.sqrt(gr * gr + gc * gc), cos_c, sin_c, acc)
            for b in range(cos_c.size):
                out[ci, cj, b] = acc[b] / area


@njit(cache=True, nogil=True)
def zero_angle_votes(img, cell_px, n_cr, n_cc, out):  # pragma: no cover - jit
    """Per cell, the votes of gradients at exactly 0 degrees (``g_row == 0``, ``g_col != 0``), / cell area.

    Same gradients and borders as :func:`hist_from_image` (a grey image of
    any real dtype); one bin per vote puts all of them into the first bin.
    """
    h, w = img.shape
    area = cell_px * cell_px
    for ci in range(n_cr):
        for cj in range(n_cc):
            acc = 0.0
            for r in range(ci * cell_px, ci * cell_px + cell_px):
                row_in = 0 < r < h - 1
                for c in range(cj * cell_px, cj * cell_px + cell_px):
                    gr = float(img[r + 1, c]) - float(img[r - 1, c]) if row_in else 0.0
                    if gr != 0.0:
                        continue
                    acc += abs(float(img[r, c + 1]) - float(img[r, c - 1]) if 0 < c < w - 1 else 0.0)
            out[ci, cj] = acc / area


@njit(cache=True, nogil=True)
def normalize_kernel(hist, b, method, out):  # pragma: no cover - jit
    """skimage's _hog_normalize_block for every block; method indexes BLOCK_NORMS.

    Block sums are assembled from per-cell sums and divisions are done as
    multiplications by the reciprocal (results agree with skimage to a few ulp).
    """
    n, m, k = out.shape
    n_r, n_c, bins = hist.shape
    eps = 1e-5
    cell_s1 = np.zeros((n_r, n_c))
    cell_s2 = np.zeros((n_r, n_c))
    for r in range(n_r):
        for c in range(n_c):
            s1 = 0.0
            s2 = 0.0
            for o in range(bins):
                x = hist[r, c, o]
                s1 += x
                s2 += x * x
            cell_s1[r, c] = s1
            cell_s2[r, c] = s2
    for i in range(n):
        for j in range(m):
            s1 = 0.0
            s2 = 0.0
            for di in range(b):
                for dj in range(b):
                    s1 += cell_s1[i + di, j + dj]
                    s2 += cell_s2[i + di, j + dj]
            if method >= 2:  # L1, L1-sqrt (histograms are >= 0, so |x| = x)
                inv = 1.0 / (s1 + eps)
            else:
                inv = 1.0 / math.sqrt(s2 + eps * eps)
            t = 0
            h2 = 0.0
            for di in range(b):
                for dj in range(b):
                    for o in range(bins):
                        x = hist[i + di, j + dj, o] * inv
                        if method == 3:
                            x = math.sqrt(x)
                        elif method == 0:  # L2-Hys: clip at 0.2, renormalise below
                            x = min(x, 0.2)
                            h2 += x * x
                        out[i, j, t] = x
                        t += 1
            if method == 0:
                inv = 1.0 / math.sqrt(h2 + eps * eps)
                for t in range(k):
                    out[i, j, t] *= inv
