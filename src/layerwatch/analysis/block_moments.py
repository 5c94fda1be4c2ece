"""Per-block means of two textures, their squares and their product in one pass: OpenCV's values.

The nothing-extruded check (:func:`layerwatch.analysis.extrusion.block_ncc`) and the layer-change
channel's noise calibration (:func:`layerwatch.analysis.layer_change.pair_noise`) average ``a``,
``b``, ``a a``, ``b b`` and ``a b`` (each times a 0/1 weight in the check) over square blocks, each
by its own ``cv2.resize(..., INTER_AREA)`` of a product NumPy made first: five products and five
passes over a working box. :func:`block_moments` reads ``a``, ``b`` (and the weight) once and gives
the five means bit for bit as those calls did: each product is the same float32 product, and each
block's sum follows OpenCV's "area fast" path for a whole factor (``ResizeAreaFast_Invoker``, the
block's values in row-major order, four at a time as ``sum += ((v0 + v1) + v2) + v3``, the rest one
at a time, times ``1.f / area``). Blocks of 2 px go to OpenCV (its SIMD path adds in another order).
The tests compare the five means with OpenCV's on random, tied and signed textures and masks.
"""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit

__all__ = ["block_moments"]


@njit(cache=True, inline="always")
def _products(a, b, w, weighted, r, c):
    """The five products of pixel ``(r, c)`` as NumPy forms them: ``a``, ``b``, ``a a``, ``b b``, ``a b`` (times ``w``)."""
    x, y = a[r, c], b[r, c]
    if weighted:
        f = w[r, c]
        return x * f, y * f, (x * x) * f, (y * y) * f, (x * y) * f
    return x, y, x * x, y * y, x * y


@njit(cache=True)
def _moments4(a, b, w, weighted, bp, out):
    """:func:`_moments` for blocks of a multiple of 4 px: each row's groups of four, without branches."""
    n, m = out.shape[1], out.shape[2]
    scale = np.float32(1.0) / np.float32(bp * bp)
    for i in range(n):
        for j in range(m):
            s0 = s1 = s2 = s3 = s4 = np.float32(0.0)
            for sy in range(bp):
                r = i * bp + sy
                for c in range(j * bp, (j + 1) * bp, 4):
                    p0, p1, p2, p3, p4 = _products(a, b, w, weighted, r, c)
                    q0, q1, q2, q3, q4 = _products(a, b, w, weighted, r, c + 1)
                    t0, t1, t2, t3, t4 = _products(a, b, w, weighted, r, c + 2)
                    u0, u1, u2, u3, u4 = _products(a, b, w, weighted, r, c + 3)
                    s0 += ((p0 + q0) + t0) + u0
                    s1 += ((p1 + q1) + t1) + u1
                    s2 += ((p2 + q2) + t2) + u2
                    s3 += ((p3 + q3) + t3) + u3
                    s4 += ((p4 + q4) + t4) + u4
            out[0, i, j], out[1, i, j], out[2, i, j] = s0 * scale, s1 * scale, s2 * scale
            out[3, i, j], out[4, i, j] = s3 * scale, s4 * scale


@njit(cache=True)
def _moments(a, b, w, weighted, bp, out):
    """``out[q, i, j]``: the mean over block ``(i, j)`` of ``a``, ``b``, ``a a``, ``b b``, ``a b`` (``q`` = 0..4),
    each times ``w`` when ``weighted``; ``a``, ``b``, ``w`` (n bp, m bp) float32, ``out`` (5, n, m) float32."""
    n, m = out.shape[1], out.shape[2]
    area = bp * bp
    grouped = area // 4 * 4
    scale = np.float32(1.0) / np.float32(area)
    for i in range(n):
        for j in range(m):
            s0 = s1 = s2 = s3 = s4 = np.float32(0.0)
            g0 = g1 = g2 = g3 = g4 = np.float32(0.0)
            k = 0
            for sy in range(bp):
                r = i * bp + sy
                for sx in range(bp):
                    c = j * bp + sx
                    v0, v1, v2, v3, v4 = _products(a, b, w, weighted, r, c)
                    if k < grouped:
                        if k % 4 == 0:
                            g0, g1, g2, g3, g4 = v0, v1, v2, v3, v4
                        else:
                            g0, g1, g2, g3, g4 = g0 + v0, g1 + v1, g2 + v2, g3 + v3, g4 + v4
                        if k % 4 == 3:
                            s0, s1, s2, s3, s4 = s0 + g0, s1 + g1, s2 + g2, s3 + g3, s4 + g4
                    else:
                        s0, s1, s2, s3, s4 = s0 + v0, s1 + v1, s2 + v2, s3 + v3, s4 + v4
                    k += 1
            out[0, i, j], out[1, i, j], out[2, i, j] = s0 * scale, s1 * scale, s2 * scale
            out[3, i, j], out[4, i, j] = s3 * scale, s4 * scale


def block_moments(a: np.ndarray, b: np.ndarray, block_px: int,
                  weight: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Block means of ``a``, ``b``, ``a * a``, ``b * b`` and ``a * b`` (each times ``weight`` when given).

    Parameters
    ----------
    a, b : ndarray, float32, shape (h, w)
        Textures (cut to whole blocks: rows and columns beyond the last whole block are left out).
    block_px : int
        Block side, px (>= 1).
    weight : ndarray, float32, shape (h, w), optional
        Per-pixel weight multiplied into each product (0/1: a mask).

    Returns
    -------
    tuple of 5 ndarray, float32, shape (h // block_px, w // block_px)
        ``cv2.resize(v[:n bp, :m bp], (m, n), interpolation=cv2.INTER_AREA)`` for ``v`` = ``a``, ``b``,
        ``a * a``, ``b * b``, ``a * b`` (times ``weight``), bit for bit.

    Raises
    ------
    ValueError
        Shapes that differ, not 2-D, or a block under 1 px.
    """
    bp = int(block_px)
    a32, b32 = np.asarray(a, np.float32), np.asarray(b, np.float32)
    if a32.ndim != 2 or a32.shape != b32.shape or (weight is not None and np.shape(weight) != a32.shape) or bp < 1:
        raise ValueError(f"block_moments needs two equal 2-D textures (and weight), got {a32.shape}, {b32.shape}"
                         f"{'' if weight is None else f', {np.shape(weight)}'}, block {bp}")
    n, m = a32.shape[0] // bp, a32.shape[1] // bp
    crop = (slice(0, n * bp), slice(0, m * bp))
    x, y = np.ascontiguousarray(a32[crop]), np.ascontiguousarray(b32[crop])
    k = None if weight is None else np.ascontiguousarray(np.asarray(weight, np.float32)[crop])
    if bp <= 2 or n == 0 or m == 0:  # OpenCV's own calls (its 2 x 2 path sums in another order)
        vals = [x, y, x * x, y * y, x * y]
        return tuple(cv2.resize(v if k is None else v * k, (m, n), interpolation=cv2.INTER_AREA) for v in vals)
    out = np.empty((5, n, m), np.float32)
    (_moments4 if bp % 4 == 0 else _moments)(x, y, x if k is None else k, k is not None, bp, out)
    return out[0], out[1], out[2], out[3], out[4]
