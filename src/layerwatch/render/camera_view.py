"""The reference as the calibrated camera sees it, brought back onto the layer plane.

A photo warped into the top view of the plane ``Z = z`` (eq. 3) is exact
only for points *on* that plane. Everything else reaches the top view along
the camera's rays: the walls of the part facing the camera appear as a band
in front of its edge, the floor of a hole or the layers below a sparse infill
appear shifted towards the camera (parallax), and the part hides what lies
behind its walls. An orthographic top view of the ideal layer has none of
this, so clean layers lose similarity wherever the print is not flat.

:func:`view_from_camera` gives the reference exactly that geometry: for every
top-view pixel ``P`` on the plane ``Z = z`` it follows the ray from the
camera centre ``C`` through ``P`` on into the rendered height map and takes
the first surface it meets: a top surface shows its shaded value (the fast
renderer's shading at the hit point), a wall shows the wall brightness with
the layer lines a wall has; a ray that reaches the bed shows the bed. The
result is what warping a camera photo of the rendered scene with the same
homography would give, without rendering the camera image first (so no
resampling loss and no dependence on the camera's resolution).

References
----------
Petsiuk & Pearce (2022), Section 2.3, eqs. (1)-(3) (the plane homography
whose rays are followed here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from layerwatch.geometry.topview import TopView

__all__ = ["DEFAULT_LOOK", "SKIP_PX", "WallLook", "bilinear", "grown_box", "ray_setup", "skip_map", "view_from_camera", "wall_light"]

#: half-side (px) of the square over which :func:`skip_map` takes the maximum height
SKIP_PX = 8


@njit(cache=True)
def bilinear(img, x, y):
    """Bilinear sample of ``img`` (H, W) at pixel ``(x, y)``, clamped to the image."""
    H, W = img.shape
    x = min(max(x, 0.0), W - 1.0)
    y = min(max(y, 0.0), H - 1.0)
    x0 = min(int(x), W - 2) if W > 1 else 0
    y0 = min(int(y), H - 2) if H > 1 else 0
    fx = x - x0
    fy = y - y0
    x1 = min(x0 + 1, W - 1)
    y1 = min(y0 + 1, H - 1)
    top = img[y0, x0] * (1.0 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1.0 - fx) + img[y1, x1] * fx
    return top * (1.0 - fy) + bot * fy


@njit(cache=True)
def wall_light(facing, z, layer_h, wall_value, wall_ambient, line_contrast):
    """Brightness of a wall point at height ``z`` (mm) whose normal makes cosine ``facing`` with the view.

    ``wall_value * (wall_ambient + (1 - wall_ambient) * facing)``, darkened by
    ``line_contrast`` on the layer lines (period ``layer_h``).
    """
    ph = z / layer_h if layer_h > 0 else 0.0
    lines = 0.5 * (1.0 + math.cos(2.0 * math.pi * ph))
    return wall_value * (wall_ambient + (1.0 - wall_ambient) * facing) * (1.0 - line_contrast * lines)


@njit(cache=True, inline="always")
def _wall_facing(height, xi, yi, du, dv, L):
    """Cosine between the wall normal at pixel ``(xi, yi)`` and the top-view direction ``(du, dv) / L`` to it.

    The normal is the central-difference gradient of ``height``; a flat
    neighbourhood (no gradient) counts as facing the camera squarely (1).
    """
    H, W = height.shape
    xm = max(xi - 1, 0)
    xp = min(xi + 1, W - 1)
    ym = max(yi - 1, 0)
    yp = min(yi + 1, H - 1)
    gx = height[yi, xp] - height[yi, xm]
    gy = height[yp, xi] - height[ym, xi]
    g = math.sqrt(gx * gx + gy * gy)
    facing = 1.0
    if g > 1e-9:
        facing = max((gx * du + gy * dv) / (g * L), 0.0)
    return facing


@njit(cache=True)
def _march(height, hmax, skip_px, shaded, cu, cv, cz, z, step_px, max_steps, wall_value, wall_ambient,
           line_contrast, layer_h, out, hit_z):
    """Follow the camera ray through every top-view pixel into the height map.

    ``(cu, cv)`` is the camera centre in top-view pixels, ``cz`` its height
    over the bed (mm, above ``z``); ``hmax`` is ``height`` dilated by
    ``skip_px`` (max over the square of that half-side), which lets a ray skip
    empty space in strides of ``skip_px``; see :func:`view_from_camera`.
    """
    H, W = height.shape
    for v in range(H):
        for u in range(W):
            du = u - cu
            dv = v - cv
            L = math.sqrt(du * du + dv * dv)
            if L < 1e-6:  # looking straight down: the plane point itself
                out[v, u] = shaded[v, u]
                hit_z[v, u] = height[v, u]
                continue
            dt = step_px / L
            dx = du * dt
            dy = dv * dt
            dz = dt * (cz - z)  # descent per step, mm
            x = float(u)
            y = float(v)
            zz = z
            val = shaded[v, u]
            hz = height[v, u]
            jump = skip_px / step_px  # steps covered by one skip
            k = 0
            hit = False
            while k < max_steps:
                xi = int(x + 0.5)
                yi = int(y + 0.5)
                if xi < 0 or yi < 0 or xi >= W or yi >= H:
                    # left the rendered square: what lies there is bed or unknown
                    val = bilinear(shaded, x, y)
                    hz = 0.0
                    hit = True
                    break
                if k > 0 and hmax[yi, xi] < zz - jump * dz and zz - jump * dz > 0.0:
                    # nothing within skip_px reaches the ray over the next skip_px: skip ahead
                    x += dx * jump
                    y += dy * jump
                    zz -= dz * jump
                    k += int(jump)
                    continue
                h = height[yi, xi]
                if h >= zz:
                    if k > 0 and h - zz > 1.5 * dz:
                        # entered the column through its side: a wall facing the camera,
                        # lit as seen from the camera (cosine of its normal to the view)
                        facing = _wall_facing(height, xi, yi, du, dv, L)
                        val = wall_light(facing, zz, layer_h, wall_value, wall_ambient, line_contrast)
                        hz = zz
                    else:
                        val = bilinear(shaded, x, y)
                        hz = h
                    hit = True
                    break
                if zz <= 0.0:
                    val = bilinear(shaded, x, y)
                    hz = 0.0
                    hit = True
                    break
                x += dx
                y += dy
                zz -= dz
                k += 1
            if not hit:  # max_depth_mm reached: what lies under the ray there
                val = bilinear(shaded, x, y)
                hz = height[min(max(int(y + 0.5), 0), H - 1), min(max(int(x + 0.5), 0), W - 1)]
            out[v, u] = val
            hit_z[v, u] = hz


@dataclass(frozen=True)
class WallLook:
    """How the camera-view ray march draws walls, and how far it follows a ray.

    Shared by :func:`view_from_camera` and
    :func:`~layerwatch.render.volume.view_through_volume`.

    Attributes
    ----------
    layer_height_mm : float
        Period of the layer lines drawn on walls, mm.
    wall_value : float
        Brightness (0-1) of a wall facing the camera squarely.
    wall_line_contrast : float
        Depth of the layer lines on walls, fraction of ``wall_value``.
    wall_ambient : float
        Share of ``wall_value`` a wall keeps whatever its orientation; the rest
        falls with the cosine between its normal and the direction to the
        camera (a light at the camera, as a ring light round the lens).
    step_px : float
        Horizontal step of the ray march, top-view pixels.
    max_depth_mm : float
        A ray that has descended this far below ``z`` without a hit shows
        what lies under it there (tall parts: bounds the work per pixel).
    """

    layer_height_mm: float = 0.2
    wall_value: float = 0.55
    wall_line_contrast: float = 0.2
    wall_ambient: float = 1.0
    step_px: float = 0.75
    max_depth_mm: float = 30.0


#: The default :class:`WallLook`.
DEFAULT_LOOK = WallLook()


def view_from_camera(
    height: np.ndarray,
    shaded: np.ndarray,
    center_mm: np.ndarray,
    topview: TopView,
    z: float,
    *,
    look: WallLook = DEFAULT_LOOK,
) -> tuple[np.ndarray, np.ndarray]:
    """Resample a rendered top view along the camera's rays (see module notes).

    Parameters
    ----------
    height : ndarray, shape (H, W), float32
        Rendered height map of the layers so far, mm (0 = bed).
    shaded : ndarray, shape (H, W), float32
        Shaded top view (albedo x light, 0-1) of the same scene.
    center_mm : ndarray, shape (3,)
        Camera centre in bed mm (``CameraModel.center_mm``); must lie above ``z``.
    topview : TopView
        Frame of ``height``/``shaded`` and of the result.
    z : float
        Height of the plane the photo is warped to (the layer's top), mm.
    look : WallLook
        How walls look and how far rays are marched.

    Returns
    -------
    image : ndarray, shape (H, W), float32
        What the camera sees through each point of the plane, 0-1.
    hit_z : ndarray, shape (H, W), float32
        Height of the surface each ray met, mm.
    """
    c, cu, cv, max_steps = ray_setup(center_mm, topview, z, look.step_px, look.max_depth_mm)
    h = np.ascontiguousarray(height, np.float32)
    s = np.ascontiguousarray(shaded, np.float32)
    out = np.empty_like(s)
    hit = np.empty_like(h)
    skip = SKIP_PX
    hmax = skip_map(h, skip)
    _march(h, hmax, float(skip), s, float(cu), float(cv), float(c[2]), float(z), float(look.step_px), max_steps,
           float(look.wall_value), float(look.wall_ambient), float(look.wall_line_contrast),
           float(look.layer_height_mm), out, hit)
    return out, hit


def ray_setup(center_mm, topview: TopView, z: float, step_px: float, max_depth_mm: float):
    """Checked camera centre and the ray march's bounds for the plane ``Z = z``.

    Returns
    -------
    c : ndarray, shape (3,)
        Camera centre, bed mm.
    cu, cv : float
        Its position in top-view pixels.
    max_steps : int
        Steps that let the flattest ray over the square descend ``max_depth_mm``
        (or down to the bed).

    Raises
    ------
    ValueError
        The centre is not three finite numbers or does not lie above ``z``.
    """
    c = np.asarray(center_mm, np.float64).reshape(-1)
    if c.size != 3 or not np.all(np.isfinite(c)):
        raise ValueError("center_mm must be the camera centre (x, y, z) in bed mm")
    if c[2] <= z:
        raise ValueError(f"the camera (z = {c[2]:.1f} mm) must be above the layer plane (z = {z:.1f} mm)")
    cu, cv = topview.to_px(c[:2])
    corners = topview.to_px(topview.corners_mm)
    near = max(float(np.min(np.hypot(corners[:, 0] - cu, corners[:, 1] - cv))), 1.0)
    far = max(float(np.max(np.hypot(corners[:, 0] - cu, corners[:, 1] - cv))), near)
    # descent per step is step_px / L * (cz - z); the smallest descent (largest L) needs most steps
    min_dz = step_px / far * (c[2] - z)
    max_steps = int(min(max_depth_mm, max(z, 0.0) + 1.0) / max(min_dz, 1e-6)) + 2
    return c, float(cu), float(cv), max_steps


def skip_map(height: np.ndarray, skip: int = SKIP_PX, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """``height`` dilated over squares of half-side ``skip`` px: lets a ray skip empty space.

    ``box`` ``(r0, r1, c0, c1)``: rows and columns outside which ``height`` is 0 (a renderer's printed box; None:
    anywhere). Only the box grown by ``skip + 1`` is dilated and the rest is 0: the whole dilation's values (every
    square that reaches the box lies in the grown box, whose replicated border is 0 as the map beyond it is, or is
    the map's own border), for the box's cost.
    """
    k = np.ones((2 * skip + 1, 2 * skip + 1), np.uint8)
    if box is None:
        return cv2.dilate(height, k, borderType=cv2.BORDER_REPLICATE)
    out = np.zeros_like(height)
    g = grown_box(box, skip + 1, height.shape)
    if g is not None:
        out[g] = cv2.dilate(np.ascontiguousarray(height[g]), k, borderType=cv2.BORDER_REPLICATE)
    return out


def grown_box(box: tuple[int, int, int, int], by: int, shape: tuple[int, ...]) -> tuple[slice, slice] | None:
    """Rows and columns of ``box`` ``(r0, r1, c0, c1)`` grown by ``by`` px within ``shape``; None when it is empty."""
    r0, r1, c0, c1 = box
    if r1 <= r0 or c1 <= c0:
        return None
    return slice(max(r0 - by, 0), min(r1 + by, shape[0])), slice(max(c0 - by, 0), min(c1 + by, shape[1]))
