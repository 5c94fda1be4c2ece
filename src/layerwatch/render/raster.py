"""Numba kernels: beads (capsules) into a height map, and its shading.

A bead is the set of points within ``r = w / 2`` of its segment (a capsule).
Each capsule is scanned row by row: for row ``v`` only the columns near the
part of the segment whose ``y`` lies within ``[v - r, v + r]`` are visited,
so long diagonal lines cost their area, not their bounding box. A pixel
belongs to a bead when its centre is inside the capsule (OpenCV pixel-centre
convention, see :mod:`layerwatch.geometry.topview`).

Cross-section height (rounded top of a bead of height ``h`` whose top is at
``z``; ``d`` is the distance to the centre line)::

    z(d) = z - h / 2 + (h / 2) * sqrt(1 - (d / r) ** 2)

References
----------
Petsiuk & Pearce (2022), Section 2.4: the reference is the ideal layer as the
camera would see it under the ring light.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["raster_capsules", "shade_height", "ring_lights", "directional_light"]


@njit(cache=True)
def raster_capsules(height, mask, p0, p1, r, ztop, hh, write_height, write_mask):
    """Rasterise capsules into ``height`` (max z-buffer) and/or ``mask``.

    Parameters
    ----------
    height : ndarray, shape (H, W), float32
        Height map in mm, updated in place with the per-pixel maximum.
    mask : ndarray, shape (H, W), bool
        Footprint, set to True under every capsule (when ``write_mask``).
    p0, p1 : ndarray, shape (S, 2), float64
        Segment endpoints in pixel coordinates ``(u, v)``.
    r : ndarray, shape (S,), float64
        Capsule radius in pixels.
    ztop, hh : ndarray, shape (S,), float64
        Top of the bead and bead height, mm.
    write_height, write_mask : bool

    Returns
    -------
    int
        Number of capsules that were (partly) outside the image.
    """
    H, W = height.shape
    clipped = 0
    for i in range(p0.shape[0]):
        ax, ay = p0[i, 0], p0[i, 1]
        bx, by = p1[i, 0], p1[i, 1]
        ri = r[i]
        if not (ri > 0.0):
            continue
        r2 = ri * ri
        dx, dy = bx - ax, by - ay
        l2 = dx * dx + dy * dy
        inv = 1.0 / l2 if l2 > 1e-12 else 0.0
        vlo = math.ceil(min(ay, by) - ri)
        vhi = math.floor(max(ay, by) + ri)
        ulo_all = math.ceil(min(ax, bx) - ri)
        uhi_all = math.floor(max(ax, bx) + ri)
        if vlo < 0 or ulo_all < 0 or vhi > H - 1 or uhi_all > W - 1:
            clipped += 1
        vlo = max(vlo, 0)
        vhi = min(vhi, H - 1)
        half = 0.5 * hh[i]
        base = ztop[i] - half
        for v in range(vlo, vhi + 1):
            # parameter range of the segment points with |y - v| <= r
            if abs(dy) < 1e-12:
                if abs(v - ay) > ri:
                    continue
                t_lo, t_hi = 0.0, 1.0
            else:
                t1 = (v - ri - ay) / dy
                t2 = (v + ri - ay) / dy
                t_lo = max(min(t1, t2), 0.0)
                t_hi = min(max(t1, t2), 1.0)
                if t_lo > t_hi:
                    continue
            xa = ax + t_lo * dx
            xb = ax + t_hi * dx
            ulo = max(math.ceil(min(xa, xb) - ri), 0)
            uhi = min(math.floor(max(xa, xb) + ri), W - 1)
            py = v - ay
            for u in range(ulo, uhi + 1):
                px = u - ax
                t = (px * dx + py * dy) * inv
                if t < 0.0:
                    t = 0.0
                elif t > 1.0:
                    t = 1.0
                qx = px - t * dx
                qy = py - t * dy
                d2 = qx * qx + qy * qy
                if d2 < r2:
                    if write_mask:
                        mask[v, u] = True
                    if write_height:
                        z = base + half * math.sqrt(1.0 - d2 / r2)
                        if z > height[v, u]:
                            height[v, u] = z
    return clipped


def ring_lights(elevation_deg: float, n: int = 12) -> np.ndarray:
    """Unit directions towards ``n`` lights on a ring around the vertical, shape (n, 3)."""
    el = np.radians(elevation_deg)
    az = np.arange(n) * (2 * np.pi / n)
    return np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(n, np.sin(el))], axis=1
    )


def directional_light(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit direction towards one light, shape (1, 3); azimuth from +X towards +Y."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]])


@njit(cache=True, inline="always")
def _lambert(gx, gy, lights, ambient, k, flat):
    """Light factor (<= 1) of a surface of slope ``(gx, gy)`` (mm per mm) under the lights (:func:`shade_height`)."""
    nz = 1.0 / math.sqrt(gx * gx + gy * gy + 1.0)
    nx = -gx * nz
    ny = -gy * nz
    diff = 0.0
    for j in range(k):
        d = nx * lights[j, 0] + ny * lights[j, 1] + nz * lights[j, 2]
        if d > 0.0:
            diff += d
    light = ambient + (1.0 - ambient) * diff / (k * flat)
    return 1.0 if light > 1.0 else light


@njit(cache=True)
def shade_height(height, z_top, px_per_mm, lights, ambient, depth_scale, depth_dark, out):
    """Lambertian shading of a height map under the given lights.

    Parameters
    ----------
    height : ndarray, shape (H, W), float32
        Surface height, mm (0 = bed).
    z_top : float
        Top of the current layer, mm; depth below it darkens the surface.
    px_per_mm : float
        Top-view scale (for the slope of the height map).
    lights : ndarray, shape (K, 3), float64
        Unit directions towards the lights (bed frame, +Z up), equal weights.
    ambient : float
        Ambient fraction in [0, 1].
    depth_scale : float
        Depth (mm) at which the darkening reaches ``depth_dark``; <= 0 makes
        anything below ``z_top`` fully darkened.
    depth_dark : float
        Brightness lost at ``depth_scale`` of depth.
    out : ndarray, shape (H, W), float32
        Light factor in [0, 1] (flat, top surface = 1).
    """
    H, W = height.shape
    k = lights.shape[0]
    flat = 0.0
    for j in range(k):
        flat += max(lights[j, 2], 0.0)
    flat = max(flat / k, 1e-6)
    half_s = 0.5 * px_per_mm
    level = _lambert(0.0, 0.0, lights, ambient, k, flat)  # a level pixel (most of the bed and of top surfaces)
    # a row at a time: slopes, normals, then the lights one after the other over the whole row (loops without
    # branches that the compiler vectorises), then the light factor: per pixel the operations of _lambert in its
    # order (each light's term added in turn when positive), so the values are the pixel-at-a-time ones
    gx, gy = np.empty(W), np.empty(W)
    nx, ny, nz, diff = np.empty(W), np.empty(W), np.empty(W), np.empty(W)
    for v in range(H):
        vm = max(v - 1, 0)
        vp = min(v + 1, H - 1)
        for u in range(W):
            um = max(u - 1, 0)
            up = min(u + 1, W - 1)
            gx[u] = (height[v, up] - height[v, um]) * half_s * (2.0 / max(up - um, 1))
            # image rows grow towards -Y of the bed
            gy[u] = -(height[vp, u] - height[vm, u]) * half_s * (2.0 / max(vp - vm, 1))
        for u in range(W):
            n = 1.0 / math.sqrt(gx[u] * gx[u] + gy[u] * gy[u] + 1.0)
            nx[u] = -gx[u] * n
            ny[u] = -gy[u] * n
            nz[u] = n
            diff[u] = 0.0
        for j in range(k):
            lx, ly, lz = lights[j, 0], lights[j, 1], lights[j, 2]
            for u in range(W):
                d = nx[u] * lx + ny[u] * ly + nz[u] * lz
                diff[u] = diff[u] + d if d > 0.0 else diff[u]
        for u in range(W):
            light = ambient + (1.0 - ambient) * diff[u] / (k * flat)
            light = 1.0 if light > 1.0 else light
            if gx[u] == 0.0 and gy[u] == 0.0:
                light = level
            h = height[v, u]
            if h > 0.0:
                depth = z_top - h
                if depth < 0.0:
                    depth = 0.0
                if depth_scale > 0.0:
                    f = depth / depth_scale
                    if f > 1.0:
                        f = 1.0
                else:
                    f = 1.0 if depth > 1e-4 else 0.0
                light *= 1.0 - depth_dark * f
            out[v, u] = light
