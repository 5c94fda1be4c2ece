"""Camera-view ray caster and shader of the simulator's height field.

For every camera pixel the ray ``C + t d`` (bed frame, undistorted through the
camera model) is marched from the plane ``z = zmax`` down to the bed through
the height field (steps of 0.7 grid cells, linear refinement of the hit), so
tall parts occlude and show parallax exactly as a real camera sees them.
Hits are shaded with Blinn-Phong under a spot light placed beside the camera
plus an overhead fill and an ambient term darkened by a cavity (ambient
occlusion-like) map; vertical walls get layer lines. Rays that miss the part
hit a procedural textured bed with white dot markers.

References
----------
Blinn (1977), "Models of light reflection for computer synthesized pictures".
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["render_view", "bed_albedo_image", "bed_albedo_at", "finish"]


@njit(cache=True, inline="always")
def _hash(ix, iy, seed):
    n = (ix * 374761393 + iy * 668265263 + seed * 982451653) & 0xFFFFFFFF
    n = ((n ^ (n >> 13)) * 1274126177) & 0xFFFFFFFF
    n = n ^ (n >> 16)
    return (n & 0xFFFF) / 65535.0


@njit(cache=True)
def _value_noise(x, y, seed):
    ix, iy = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - ix, y - iy
    fx = fx * fx * (3.0 - 2.0 * fx)
    fy = fy * fy * (3.0 - 2.0 * fy)
    a = _hash(ix, iy, seed)
    b = _hash(ix + 1, iy, seed)
    c = _hash(ix, iy + 1, seed)
    d = _hash(ix + 1, iy + 1, seed)
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


@njit(cache=True)
def _bed_albedo(x, y, bed, bed_rgb, bg_rgb, markers, marker_r, seed, out):
    if x < bed[0] or x > bed[2] or y < bed[1] or y > bed[3]:
        g = 0.8 + 0.4 * _value_noise(x * 0.05, y * 0.05, seed + 3)
        for c in range(3):
            out[c] = bg_rgb[c] * g
        return
    g = 0.82 + 0.25 * _value_noise(x * 0.8, y * 0.8, seed) + 0.12 * _hash(
        int(np.floor(x * 9.0)), int(np.floor(y * 9.0)), seed + 1
    )
    for c in range(3):
        out[c] = bed_rgb[c] * g
    for m in range(markers.shape[0]):
        dx, dy = x - markers[m, 0], y - markers[m, 1]
        d = np.sqrt(dx * dx + dy * dy)
        if d < marker_r + 0.15:
            w = min(max((marker_r + 0.15 - d) / 0.3, 0.0), 1.0)
            for c in range(3):
                out[c] = out[c] * (1 - w) + 0.93 * w


@njit(cache=True, inline="always")
def _solid_at(h, gap, v, u, z, z_prev):
    """Is height ``z`` of cell ``(v, u)`` material? Below the top ``h`` and not in the cell's gap.

    A ray that was above the gap's top at its previous sample (``z_prev``) has
    crossed the material over the gap: solid (thin skins stay opaque at any step).
    """
    if z > h[v, u]:
        return False
    lo, hi = gap[v, u, 0], gap[v, u, 1]
    if lo <= 0.0:  # a gap down to the bed: the ray's last sample on the bed plane is not material
        lo = -1.0
    return not (lo < z < hi and z_prev < hi)


@njit(cache=True, inline="always")
def _clip_to_bbox(C, d0, d1, ta, tb, bbox):
    """Clip the ray interval ``[ta, tb]`` to the x and y slabs of ``bbox``: ``(ok, ta, tb)``.

    ``ok`` is false when the ray runs parallel to a slab outside it.
    """
    ok = True
    for ax in range(2):
        o = C[ax]
        dd = d0 if ax == 0 else d1
        lo, hi = bbox[ax], bbox[ax + 2]
        if abs(dd) < 1e-12:
            if o < lo or o > hi:
                ok = False
        else:
            t1, t2 = (lo - o) / dd, (hi - o) / dd
            if t1 > t2:
                t1, t2 = t2, t1
            ta = max(ta, t1)
            tb = min(tb, t2)
    return ok, ta, tb


@njit(cache=True, inline="always")
def _part_surface(m, wall, gv, gu, d0, d1, pz, nrm, wn, albedo, layer_h, alb):
    """Albedo (into ``alb``, 3) and unit normal ``(nx, ny, nz)`` of the part where a ray hit cell ``(gv, gu)``.

    A wall takes the smoothed horizontal gradient ``wn`` as its normal (the
    reversed ray where that is too weak) and, for the part material
    (``m == 1``), layer lines of period ``layer_h`` mm in height ``pz``.
    """
    for c in range(3):
        alb[c] = albedo[m, c]
    if not wall:
        return nrm[gv, gu, 0], nrm[gv, gu, 1], nrm[gv, gu, 2]
    nx, ny = wn[gv, gu, 0], wn[gv, gu, 1]
    nn = np.sqrt(nx * nx + ny * ny)
    if nn < 0.2:
        nx, ny, nn = -d0, -d1, np.sqrt(d0 * d0 + d1 * d1)
    if m == 1 and layer_h > 0:
        lw = 1.0 + 0.12 * np.cos(2.0 * np.pi * pz / layer_h)
        for c in range(3):
            alb[c] *= lw
    return nx / nn, ny / nn, 0.0


@njit(cache=True, inline="always")
def _shade(C, px, py, pz, nx, ny, nz, occ, ks, shin, alb, light, out, i, j):
    """Blinn-Phong radiance of the point ``(px, py, pz)`` mm seen from the camera at ``C`` into ``out[i, j]``.

    Spot light (``light[0:3]`` position, ``light[3:6]`` axis, cone cosines
    ``light[6:8]``, intensity ``light[8]`` at distance ``light[11]``) plus an
    ambient (``light[9]``) and an overhead fill (``light[10]``), both darkened
    by the occlusion ``occ``; ``ks``, ``shin``: specular weight and exponent.
    """
    lx, ly, lz = light[0] - px, light[1] - py, light[2] - pz
    dist = np.sqrt(lx * lx + ly * ly + lz * lz)
    lx, ly, lz = lx / dist, ly / dist, lz / dist
    vx, vy, vz = C[0] - px, C[1] - py, C[2] - pz
    vn = np.sqrt(vx * vx + vy * vy + vz * vz)
    vx, vy, vz = vx / vn, vy / vn, vz / vn
    hx, hy, hz = lx + vx, ly + vy, lz + vz
    hn = np.sqrt(hx * hx + hy * hy + hz * hz)
    ndl = max(nx * lx + ny * ly + nz * lz, 0.0)
    ndh = max((nx * hx + ny * hy + nz * hz) / hn, 0.0)
    cosang = -(lx * light[3] + ly * light[4] + lz * light[5])
    spot = min(max((cosang - light[7]) / (light[6] - light[7]), 0.0), 1.0)
    inten = light[8] * spot * (light[11] / dist) ** 2
    amb = light[9] * occ + light[10] * max(nz, 0.0) * occ
    sp = ks * ndh**shin * inten * (1.0 if ndl > 0 else 0.0)
    for c in range(3):
        out[i, j, c] = alb[c] * (amb + ndl * inten * (0.55 + 0.45 * occ)) + sp


@njit(cache=True)
def render_view(
    dirs, C, h, mat, gap, nrm, wn, ao, s, ux0, vy0, zmax, bbox,
    albedo, spec, light, bed_alb, bg_rgb, layer_h, out,
):
    """Ray-cast and shade one camera frame (linear radiance, float32 (h, w, 3)).

    ``gap`` (H, W, 2): per cell the empty interval ``(lo, hi)`` under printed
    material (a window, the space under an overhang or a bridge; ``hi = 0``:
    none), which rays pass through.

    ``light`` = ``[Lx, Ly, Lz, ax, ay, az, cos_in, cos_out, I, ambient, fill, dref]``;
    ``bbox`` = ``(xmin, ymin, xmax, ymax)`` of cells with height > 0 (mm);
    ``nrm`` (H, W, 3) surface normals, ``wn`` (H, W, 2) smoothed horizontal
    gradients used as wall normals;
    ``albedo`` (nmat, 3) and ``spec`` (nmat, 2) = (ks, shininess) per material;
    ``bed_alb`` (h, w, 3): albedo of the bare bed seen by each pixel
    (:func:`bed_albedo_image`).
    """
    Hc, Wc = dirs.shape[0], dirs.shape[1]
    Hg, Wg = h.shape
    alb = np.zeros(3)
    step_cells = 0.7
    for i in range(Hc):
        for j in range(Wc):
            d0, d1, d2 = dirs[i, j, 0], dirs[i, j, 1], dirs[i, j, 2]
            if d2 > -1e-6:
                for c in range(3):
                    out[i, j, c] = bg_rgb[c] * light[9]
                continue
            t_bed = C[2] / (-d2)
            hit = wall = False
            px = py = pz = 0.0
            gu = gv = -1
            if zmax > 0.0:
                ok, ta, tb = _clip_to_bbox(C, d0, d1, (C[2] - zmax) / (-d2), t_bed, bbox)
                if ok and ta <= tb:
                    hs = np.sqrt(d0 * d0 + d1 * d1)
                    dt = step_cells / (s * max(hs, 1e-3))
                    t = t_prev = ta
                    f_prev = z_prev = 1e9
                    while t <= tb + dt:
                        tt = min(t, tb)
                        x, y, z = C[0] + tt * d0, C[1] + tt * d1, C[2] + tt * d2
                        u = int(ux0 + s * x + 0.5)
                        v = int(vy0 - s * y + 0.5)
                        if 0 <= u < Wg and 0 <= v < Hg:
                            hh = h[v, u]
                            f = z - hh
                            if f <= 0.0 and hh > 0.0 and _solid_at(h, gap, v, u, z, z_prev):
                                th = tt
                                if f_prev < 1e8:
                                    th = t_prev + (tt - t_prev) * f_prev / (f_prev - f)
                                px, py, pz = C[0] + th * d0, C[1] + th * d1, C[2] + th * d2
                                gu, gv = u, v
                                hit = True
                                z_up = z + 2.0 * dt * (-d2)  # entered through a side: solid just above too
                                wall = _solid_at(h, gap, v, u, z_up, z_up)
                                break
                            f_prev = f
                        t_prev = tt
                        z_prev = z
                        if t > tb:
                            break
                        t += dt
            if hit:
                m = mat[gv, gu]
                nx, ny, nz = _part_surface(m, wall, gv, gu, d0, d1, pz, nrm, wn, albedo, layer_h, alb)
                occ = ao[gv, gu]
                ks, shin = spec[m, 0], spec[m, 1]
            else:
                px, py, pz = C[0] + t_bed * d0, C[1] + t_bed * d1, 0.0
                for c in range(3):
                    alb[c] = bed_alb[i, j, c]
                nx, ny, nz = 0.0, 0.0, 1.0
                u = int(ux0 + s * px + 0.5)
                v = int(vy0 - s * py + 0.5)
                occ = ao[v, u] if (0 <= u < Wg and 0 <= v < Hg) else 1.0
                ks, shin = spec[0, 0], spec[0, 1]
            _shade(C, px, py, pz, nx, ny, nz, occ, ks, shin, alb, light, out, i, j)


@njit(cache=True)
def bed_albedo_image(dirs, C, bed, bed_rgb, bg_rgb, markers, marker_r, seed):
    """Albedo of the bare bed (textured sheet, dot markers, background) per pixel, (h, w, 3)."""
    Hc, Wc = dirs.shape[0], dirs.shape[1]
    out = np.empty((Hc, Wc, 3), np.float32)
    alb = np.zeros(3)
    for i in range(Hc):
        for j in range(Wc):
            d2 = dirs[i, j, 2]
            if d2 > -1e-6:
                for c in range(3):
                    out[i, j, c] = bg_rgb[c]
                continue
            t = C[2] / (-d2)
            _bed_albedo(C[0] + t * dirs[i, j, 0], C[1] + t * dirs[i, j, 1], bed, bed_rgb, bg_rgb,
                        markers, marker_r, seed, alb)
            for c in range(3):
                out[i, j, c] = alb[c]
    return out


@njit(cache=True)
def bed_albedo_at(x, y, bed, bed_rgb, bg_rgb, markers, marker_r, seed):
    """Albedo of the bare bed at bed points ``(x, y)`` mm (float64 (n,) each), float32 (n, 3) RGB.

    The same textured sheet, dot markers and background as :func:`bed_albedo_image`
    gives each camera pixel, at given points (the photoreal renderer's bed texture).
    """
    out = np.empty((x.shape[0], 3), np.float32)
    alb = np.zeros(3)
    for k in range(x.shape[0]):
        _bed_albedo(x[k], y[k], bed, bed_rgb, bg_rgb, markers, marker_r, seed, alb)
        for c in range(3):
            out[k, c] = alb[c]
    return out


@njit(cache=True)
def finish(img, vignette, gain, noise, oy, ox, read, shot, lut, out):
    """Sensor model: vignetting x gain, shot + read noise, gamma LUT; RGB float -> BGR uint8.

    ``noise`` is a bank of standard normals larger than the image; ``(oy, ox)``
    picks this frame's window; ``lut`` maps ``round(4095 * x)`` to 8 bits.
    """
    H, W = img.shape[0], img.shape[1]
    r2, s2 = read * read, shot * shot
    for i in range(H):
        for j in range(W):
            vg = vignette[i, j]
            for c in range(3):
                x = img[i, j, c] * vg * gain[c]
                sd = np.sqrt(r2 + s2 * max(x, 0.0))
                x += sd * noise[i + oy, j + ox, c]
                k = int(x * 4095.0 + 0.5)
                k = min(max(k, 0), 4095)
                out[i, j, 2 - c] = lut[k]
