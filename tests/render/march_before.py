"""The volume march as it was before its rays' steps were computed a row at a time (branch farmcut3): the oracle
of ``test_march_rows.py`` (a frozen copy, compiled here; not used by the package)."""

from __future__ import annotations

import math

import numpy as np  # noqa: F401 - the march's body uses it
from numba import njit

from layerwatch.render.camera_view import bilinear, wall_light
from layerwatch.render.volume import _facing, _solid


@njit(cache=False)
def march_volume_before(height, hmax, skip_px, shaded, bed, bits, r0, b0, tops, cu, cv, cz, z, step_px, max_steps, look,
                  out, hit_z, clear):
    """Follow the camera ray through every top-view pixel into the occupancy volume.

    ``look`` = ``(wall_value, wall_ambient, line_contrast, layer_h, hidden_value, depth_scale,
    depth_dark)``; ``clear`` (uint8 (H, W), :func:`clear_map` with :func:`approach_reach_px`): a ray
    that can no longer skip (the skip would pass the bed) and stands on a clear pixel meets nothing
    but the bed before it: its last steps are taken without looking (the same steps, the same
    sample: the result is identical, bit for bit); the rest as in
    :func:`~layerwatch.render.camera_view._march`. ``bits``: :attr:`OccupancyStack.bits` at its ``origin``
    ``(r0, b0)``.
    """
    H, W = height.shape
    WB = (W + 7) // 8 * 8  # the packed rows' width, where a wall's neighbours clamp
    wall_value, wall_ambient, line_contrast, layer_h = look[0], look[1], look[2], look[3]
    hidden, depth_scale, depth_dark = look[4], look[5], look[6]
    jump = skip_px / step_px
    for v in range(H):
        for u in range(W):
            du, dv = u - cu, v - cv
            L = math.sqrt(du * du + dv * dv)
            if L < 1e-6:  # looking straight down: the plane point itself
                out[v, u], hit_z[v, u] = shaded[v, u], height[v, u]
                continue
            dt = step_px / L
            dx, dy, dz = du * dt, dv * dt, dt * (cz - z)
            x, y, zz = float(u), float(v), z
            val, hz = -1.0, 0.0
            k = 0
            while k < max_steps:
                xi, yi = int(x + 0.5), int(y + 0.5)
                if xi < 0 or yi < 0 or xi >= W or yi >= H:  # left the square: bed or unknown
                    val = bilinear(shaded, x, y)
                    break
                if k > 0 and hmax[yi, xi] < zz - jump * dz and zz - jump * dz > 0.0:
                    x, y, zz, k = x + dx * jump, y + dy * jump, zz - dz * jump, k + int(jump)
                    continue
                if clear[yi, xi] != 0 and zz - jump * dz <= 0.0:  # bare bed all the way down (docstring)
                    while k < max_steps and zz > 0.0:
                        x, y, zz, k = x + dx, y + dy, zz - dz, k + 1
                    val = bilinear(shaded, x, y)
                    break
                h = height[yi, xi]
                if h >= zz and _solid(bits, r0, b0, tops, xi, yi, zz) != 0:  # (below the bed: the first slot)
                    hz = zz
                    if k == 0 or h - zz <= 1.5 * dz:  # the column's top surface
                        val, hz = bilinear(shaded, x, y), h
                    elif _solid(bits, r0, b0, tops, xi, yi, zz + 1.5 * dz) != 0:  # entered through a side: a wall
                        facing = _facing(bits, r0, b0, tops, xi, yi, zz, du, dv, L, H, WB)
                        val = wall_light(facing, zz, layer_h, wall_value, wall_ambient, line_contrast)
                    else:  # a top surface under something higher (sill, floor seen through a window)
                        f = min((z - zz) / depth_scale, 1.0) if depth_scale > 0.0 else 1.0
                        val = hidden * (1.0 - depth_dark * f)
                    break
                if zz <= 0.0:  # the bed: bare (its shaded top view) or under an overhang (its albedo)
                    val = bilinear(shaded, x, y) if h <= 0.0 else bed[yi, xi]
                    break
                x, y, zz, k = x + dx, y + dy, zz - dz, k + 1
            if val < 0.0:  # max_depth_mm reached: what lies under the ray there
                val = bilinear(shaded, x, y)
                hz = height[min(max(int(y + 0.5), 0), H - 1), min(max(int(x + 0.5), 0), W - 1)]
            out[v, u], hit_z[v, u] = val, hz
