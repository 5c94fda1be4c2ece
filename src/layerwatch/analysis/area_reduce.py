"""OpenCV's area resize of 8-bit frames by 3 and by 1.5, for less CPU: the same pixels.

A 1080p farm frame is reduced 3 x 3 twice, the camera-fault gate's grey frame (1920 -> 640 px wide,
:mod:`layerwatch.analysis.frame_quality`) and the scene channel's working image (colour, on the
print's box, :func:`layerwatch.analysis.scene_change.to_working`), and by 1.5 once, the job checks'
working image (1920 -> 1280 px, on the print's box, :func:`layerwatch.analysis.extrusion.box_texture`).

* **By 3** (OpenCV's "area fast" path): each 3 x 3 block's integer sum ``s`` times ``1 / 9``, rounded
  to the nearest integer. A sum never lies half-way (``s / 9 = q + 1/2`` needs ``2 s = 9 (2 q + 1)``,
  an odd number), so the value is ``(s + 4) // 9``, computed as ``((s + 4) * 7282) >> 16`` (equal for
  every ``s`` in 0..2295; the tests check every sum against OpenCV, for one and three channels).
  :func:`_reduce3` sums three rows per column (uint16), then three columns per channel.
* **By 1.5** (OpenCV's ``ResizeArea_Invoker`` with its ``computeResizeAreaTab`` weights, float32):
  every output pixel reads two source pixels on each axis, weighted 2/3 and 1/3 (rounded to float32)
  in the table's order. :func:`_reduce_3_2` does the same float32 products and sums in that order
  (so the same values, rounded half to even), with the pattern's indices written out instead of
  read from the table; :func:`_pair_weights` checks that OpenCV's table, computed as OpenCV does, is
  that pattern, axis by axis.

The tests compare whole frames, crops and views, odd sizes and extreme values with OpenCV. One
thread, in isolation: 1080p grey by 3 ~0.86 -> ~0.06 ms, the scene channel's 1242 x 723 colour crop
~1.2 -> ~0.2 ms, the job checks' 852 x 612 colour crop by 1.5 ~2.2 -> ~0.75 ms. Anything else
(other factors, types, channel counts, enlargements) is OpenCV's own call.
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np
from numba import njit

__all__ = ["area_resize"]


@njit(cache=True)
def _reduce3(src, cn, out):
    """``out[r, j * cn + c]``: the rounded mean of the 3 x 3 block of channel ``c`` at ``(3 r, 3 j)``.

    ``src`` (3 h, 3 w cn) uint8 (rows of interleaved pixels, any row stride), ``cn`` 1 or 3,
    ``out`` (h, w cn) uint8.
    """
    h, wc = out.shape
    n_in = src.shape[1]
    col = np.empty(n_in, np.uint16)
    hs = np.empty(wc, np.uint16)
    for r in range(h):
        a, b, c = src[3 * r], src[3 * r + 1], src[3 * r + 2]
        for i in range(n_in):
            col[i] = np.uint16(a[i]) + np.uint16(b[i]) + np.uint16(c[i])
        if cn == 1:
            for j in range(wc):
                hs[j] = col[3 * j] + col[3 * j + 1] + col[3 * j + 2]
        else:
            for j in range(wc // 3):
                q = 9 * j
                hs[3 * j] = col[q] + col[q + 3] + col[q + 6]
                hs[3 * j + 1] = col[q + 1] + col[q + 4] + col[q + 7]
                hs[3 * j + 2] = col[q + 2] + col[q + 5] + col[q + 8]
        o = out[r]
        for j in range(wc):
            o[j] = np.uint8(((np.uint32(hs[j]) + 4) * 7282) >> 16)


def _area_taps(ssize: int, dsize: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """OpenCV's area table of one axis as two taps per output pixel, or ``None`` when it has not exactly two.

    ``computeResizeAreaTab`` of OpenCV's ``resize.cpp`` (the scale as ``cv::resize`` computes it, each weight
    rounded to float32), in its order: ``(first source px, its weight, second source px, its weight)``, arrays
    of ``dsize``. A reduction by 1.5 (1920 -> 1280 px) has two taps everywhere: 2/3 and 1/3, or 1/3 and 2/3.
    """
    scale = 1.0 / (float(dsize) / float(ssize))
    taps: list[list[tuple[int, float]]] = [[] for _ in range(dsize)]
    for dx in range(dsize):
        fsx1 = dx * scale
        fsx2 = fsx1 + scale
        cell = min(scale, ssize - fsx1)
        sx2 = min(math.floor(fsx2), ssize - 1)
        sx1 = min(math.ceil(fsx1), sx2)
        if sx1 - fsx1 > 1e-3:
            taps[dx].append((sx1 - 1, (sx1 - fsx1) / cell))
        taps[dx] += [(sx, 1.0 / cell) for sx in range(sx1, sx2)]
        if fsx2 - sx2 > 1e-3:
            taps[dx].append((sx2, min(min(fsx2 - sx2, 1.0), cell) / cell))
    if any(len(t) != 2 for t in taps):
        return None
    first, second = np.array([t[0] for t in taps]), np.array([t[1] for t in taps])
    return (first[:, 0].astype(np.int64), first[:, 1].astype(np.float32),
            second[:, 0].astype(np.int64), second[:, 1].astype(np.float32))


@njit(cache=True)
def _reduce_3_2(src, cn, ax, bx, ay, by, out):
    """OpenCV's ``ResizeArea_Invoker`` (uchar, float) for a reduction by exactly 1.5 on both axes.

    Output px ``2 m`` reads source px ``3 m`` (weight ``a``) then ``3 m + 1`` (``b``), output px ``2 m + 1``
    reads ``3 m + 1`` (``b``) then ``3 m + 2`` (``a``), on both axes (:func:`_pair_weights` checks the
    tables): each source row's horizontal sums ``S[x0] w0 + S[x1] w1`` (float32, in the table's order),
    then ``w0 h0 + w1 h1`` of the two rows, rounded half to even and saturated
    (``saturate_cast<uchar>``); the same float32 operations in the same order, so the same values.
    ``src`` (H, W cn) uint8 rows of interleaved pixels (any row stride), ``cn`` 1 or 3, ``out`` (h, w cn).
    """
    h, wc = out.shape
    w = wc // cn
    hs = np.empty((3, wc), np.float32)
    lo, hi = np.float32(0.0), np.float32(255.0)
    for m in range((h + 1) // 2):
        for t in range(3 if 2 * m + 1 < h else 2):
            s, d = src[3 * m + t], hs[t]
            if cn == 3:
                for k in range(w // 2):
                    p, q = 9 * k, 6 * k
                    d[q] = np.float32(s[p]) * ax + np.float32(s[p + 3]) * bx
                    d[q + 1] = np.float32(s[p + 1]) * ax + np.float32(s[p + 4]) * bx
                    d[q + 2] = np.float32(s[p + 2]) * ax + np.float32(s[p + 5]) * bx
                    d[q + 3] = np.float32(s[p + 3]) * bx + np.float32(s[p + 6]) * ax
                    d[q + 4] = np.float32(s[p + 4]) * bx + np.float32(s[p + 7]) * ax
                    d[q + 5] = np.float32(s[p + 5]) * bx + np.float32(s[p + 8]) * ax
                if w % 2:
                    p, q = 9 * (w // 2), 3 * (w - 1)
                    for c in range(3):
                        d[q + c] = np.float32(s[p + c]) * ax + np.float32(s[p + 3 + c]) * bx
            else:
                for k in range(w // 2):
                    p = 3 * k
                    d[2 * k] = np.float32(s[p]) * ax + np.float32(s[p + 1]) * bx
                    d[2 * k + 1] = np.float32(s[p + 1]) * bx + np.float32(s[p + 2]) * ax
                if w % 2:
                    d[w - 1] = np.float32(s[3 * (w // 2)]) * ax + np.float32(s[3 * (w // 2) + 1]) * bx
        o = out[2 * m]
        for i in range(wc):
            o[i] = np.uint8(min(max(np.rint(ay * hs[0, i] + by * hs[1, i]), lo), hi))
        if 2 * m + 1 < h:
            o = out[2 * m + 1]
            for i in range(wc):
                o[i] = np.uint8(min(max(np.rint(by * hs[1, i] + ay * hs[2, i]), lo), hi))


@lru_cache(maxsize=64)
def _pair_weights(ssize: int, dsize: int) -> tuple[np.float32, np.float32] | None:
    """``(a, b)`` when OpenCV's area table of one axis (:func:`_area_taps`) is :func:`_reduce_3_2`'s pattern, else None."""
    taps = _area_taps(ssize, dsize)
    if taps is None:
        return None
    x0, w0, x1, w1 = taps
    j = np.arange(dsize)
    m, odd = j // 2, j % 2 == 1
    a, b = w0[0], w1[0]
    if not (np.array_equal(x0, 3 * m + odd) and np.array_equal(x1, 3 * m + 1 + odd)
            and np.array_equal(w0, np.where(odd, b, a)) and np.array_equal(w1, np.where(odd, a, b))):
        return None
    return np.float32(a), np.float32(b)


def area_resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``cv2.resize(img, size, interpolation=cv2.INTER_AREA)``, bit for bit.

    Parameters
    ----------
    img : ndarray
        Image as OpenCV takes it. A uint8 ``(h, w)`` or ``(h, w, 3)`` image whose pixels lie next to
        each other along its rows (a crop of a frame too), reduced by exactly 3 on both axes, is
        reduced by :func:`_reduce3`; any other goes to OpenCV.
    size : (int, int)
        Target ``(width, height)`` px.

    Returns
    -------
    ndarray, shape (height, width) or (height, width, 3), uint8 (OpenCV's type otherwise)
    """
    a = np.asarray(img)
    w, h = (int(v) for v in size)
    cn = 1 if a.ndim == 2 else a.shape[2] if a.ndim == 3 else 0
    H, W = a.shape[:2]
    if (a.dtype != np.uint8 or cn not in (1, 3) or not (1 <= w < W and 1 <= h < H) or a.strides[1] != cn
            or (cn == 3 and a.strides[2] != 1) or a.strides[0] < W * cn):
        return cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    rows = np.lib.stride_tricks.as_strided(a, (H, W * cn), (a.strides[0], 1), writeable=False)
    out = np.empty((h, w * cn), np.uint8)
    if (H, W) == (3 * h, 3 * w):
        _reduce3(rows, cn, out)
    else:
        xw, yw = _pair_weights(W, w), _pair_weights(H, h)
        if xw is None or yw is None:
            return cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        _reduce_3_2(rows, cn, *xw, *yw, out)
    return out if cn == 1 else out.reshape(h, w, 3)
