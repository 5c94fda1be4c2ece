"""Synthetic camera photos with known ground truth (for tests and the simulator).

A plane texture (the bed with its white dot markers, or a calibration
board) is drawn in bed millimetres and photographed through a
:class:`~layerwatch.geometry.camera.CameraModel` *with* lens distortion:
every (supersampled) photo pixel is undistorted, cast as a ray, intersected
with the plane and looks up the texture. Pixels whose ray misses the plane
show the background colour.

Images follow OpenCV: BGR channel order, as ``cv2.imread`` gives; colour
arguments are RGB triples.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.errors import ConfigError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.markers import _aruco_dictionary

__all__ = ["project_points", "render_plane", "render_bed_scene", "chessboard_texture"]


def project_points(camera: CameraModel, xyz_mm: np.ndarray) -> np.ndarray:
    """Project bed points to (distorted) photo pixels.

    Parameters
    ----------
    camera : CameraModel
        With pose.
    xyz_mm : ndarray, shape (n, 3) or (n, 2)
        Bed coordinates, mm (Z = 0 when only two columns).

    Returns
    -------
    ndarray, float64, shape (n, 2)
        ``(u, v)`` pixel coordinates for ``camera.image_size``.

    References
    ----------
    Petsiuk & Pearce (2022), eq. (1), plus OpenCV's distortion model.
    """
    p = np.asarray(xyz_mm, dtype=np.float64).reshape(-1, np.shape(xyz_mm)[-1])
    if p.shape[1] == 2:
        p = np.c_[p, np.zeros(len(p))]
    rvec, tvec = camera.pose
    uv = cv2.projectPoints(p.reshape(-1, 1, 3), rvec, tvec, camera.K, camera.dist)[0]
    return uv.reshape(-1, 2)


def _undistorted_normalised(camera: CameraModel, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised undistorted coordinates of every supersampled pixel, each (h*ss, w*ss)."""
    w, h = camera.image_size
    # exact undistortion on a coarse grid, bilinear in between (the field is smooth)
    step = 4
    gu = np.arange(-1, w + step + 1, step, dtype=np.float64)
    gv = np.arange(-1, h + step + 1, step, dtype=np.float64)
    U, V = np.meshgrid(gu, gv)
    pts = np.stack([U, V], -1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    n = cv2.undistortPoints(pts, camera.K, camera.dist, None, None, None, crit).reshape(len(gv), len(gu), 2)
    fu = (np.arange(w * ss) + 0.5) / ss - 0.5
    fv = (np.arange(h * ss) + 0.5) / ss - 0.5
    mx = ((fu - gu[0]) / step).astype(np.float32)
    my = ((fv - gv[0]) / step).astype(np.float32)
    MX, MY = np.meshgrid(mx, my)
    nx = cv2.remap(n[..., 0].astype(np.float32), MX, MY, cv2.INTER_LINEAR)
    ny = cv2.remap(n[..., 1].astype(np.float32), MX, MY, cv2.INTER_LINEAR)
    return nx.astype(np.float64), ny.astype(np.float64)


def render_plane(camera: CameraModel, texture: np.ndarray, texture_from_plane: np.ndarray, *,
                 z_mm: float = 0.0, background_rgb=(60, 60, 60), supersample: int = 3) -> np.ndarray:
    """Photograph a textured plane ``Z = z_mm``.

    Parameters
    ----------
    camera : CameraModel
        With pose; the photo has ``camera.image_size``.
    texture : ndarray, uint8, shape (th, tw, 3)
        BGR texture of the plane.
    texture_from_plane : ndarray, shape (3, 3)
        Affine map plane mm ``(x, y, 1)`` -> texture px ``(u, v, 1)``.
    supersample : int
        Rays per pixel along each axis (box-filtered).

    Returns
    -------
    ndarray, float32, shape (h, w, 3)
        Linear intensities 0..255 (BGR), before noise and blur.
    """
    ss = int(supersample)
    nx, ny = _undistorted_normalised(camera, ss)
    R, C = camera.R, camera.center_mm
    # ray direction in bed frame: R^T (nx, ny, 1)
    dx = R[0, 0] * nx + R[1, 0] * ny + R[2, 0]
    dy = R[0, 1] * nx + R[1, 1] * ny + R[2, 1]
    dz = R[0, 2] * nx + R[1, 2] * ny + R[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (float(z_mm) - C[2]) / dz
    hit = np.isfinite(lam) & (lam > 0)
    lam = np.where(hit, lam, 0.0)
    X = C[0] + lam * dx
    Y = C[1] + lam * dy
    A = np.asarray(texture_from_plane, dtype=np.float64)
    mu = np.where(hit, A[0, 0] * X + A[0, 1] * Y + A[0, 2], -1e5).astype(np.float32)
    mv = np.where(hit, A[1, 0] * X + A[1, 1] * Y + A[1, 2], -1e5).astype(np.float32)
    bg = tuple(float(c) for c in background_rgb[::-1])
    img = cv2.remap(texture.astype(np.float32), mu, mv, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=bg)
    if ss > 1:
        w, h = camera.image_size
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    return img


def _draw_aruco(tex, A, markers_mm, side_mm, px_per_mm, dictionary):
    d = _aruco_dictionary(dictionary)
    n = int(round(side_mm * px_per_mm))
    for i, (mx, my) in enumerate(np.asarray(markers_mm, float).reshape(-1, 2)):
        tag = cv2.aruco.generateImageMarker(d, i, n, borderBits=1).astype(np.float32)
        quiet = max(2, n // 5)
        tag = cv2.copyMakeBorder(tag, quiet, quiet, quiet, quiet, cv2.BORDER_CONSTANT, value=255)
        cu, cv_ = int(round(A[0, 0] * mx + A[0, 2])), int(round(A[1, 1] * my + A[1, 2]))
        r0, c0 = cv_ - tag.shape[0] // 2, cu - tag.shape[1] // 2
        if r0 < 0 or c0 < 0 or r0 + tag.shape[0] > tex.shape[0] or c0 + tag.shape[1] > tex.shape[1]:
            continue
        tex[r0 : r0 + tag.shape[0], c0 : c0 + tag.shape[1]] = tag[..., None] * (235 / 255)


def _bed_texture(center, extent_mm, px_per_mm, bed_rgb, texture, markers_mm, radius_mm, marker_rgb, rng):
    n = int(round(extent_mm * px_per_mm))
    tex = np.empty((n, n, 3), np.float32)
    tex[:] = np.asarray(bed_rgb[::-1], np.float32)
    if texture in ("pei", "textured"):
        grain = rng.normal(0, 1, (n // 4 + 1, n // 4 + 1)).astype(np.float32)
        grain = cv2.resize(grain, (n, n), interpolation=cv2.INTER_CUBIC)
        tex += 18.0 * grain[..., None] + rng.normal(0, 6, (n, n, 1)).astype(np.float32)
    elif texture == "grid":
        step = int(round(10 * px_per_mm))
        tex[::step, :] *= 1.4
        tex[:, ::step] *= 1.4
    elif texture != "plain":
        raise ConfigError(f"unknown bed texture {texture!r}; use 'plain', 'pei' or 'grid'.")
    A = np.array([[px_per_mm, 0, n / 2 - 0.5 - px_per_mm * center[0]],
                  [0, -px_per_mm, n / 2 - 0.5 + px_per_mm * center[1]], [0, 0, 1.0]])
    # anti-aliased discs: coverage from a signed distance, 1 px soft edge
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    col = np.asarray(marker_rgb[::-1], np.float32)
    for mx, my in np.asarray(markers_mm, float).reshape(-1, 2):
        cu, cv_ = A[0, 0] * mx + A[0, 2], A[1, 1] * my + A[1, 2]
        rpx = radius_mm * px_per_mm
        r0, r1 = int(max(cv_ - rpx - 3, 0)), int(min(cv_ + rpx + 4, n))
        c0, c1 = int(max(cu - rpx - 3, 0)), int(min(cu + rpx + 4, n))
        if r0 >= r1 or c0 >= c1:
            continue
        d = np.hypot(xx[r0:r1, c0:c1] - cu, yy[r0:r1, c0:c1] - cv_)
        a = np.clip(rpx + 0.5 - d, 0, 1)[..., None]
        tex[r0:r1, c0:c1] = tex[r0:r1, c0:c1] * (1 - a) + col * a
    return np.clip(tex, 0, 255), A


def render_bed_scene(camera: CameraModel, markers_mm: np.ndarray, marker_diameter_mm: float = 6.0, *,
                     bed_rgb=(35, 35, 38), texture: str = "plain", marker_rgb=(245, 245, 245),
                     bed_extent_mm: float = 260.0, bed_center_mm=None, background_rgb=(90, 90, 95),
                     px_per_mm: float = 10.0, glare: float = 0.0, exposure: float = 1.0,
                     noise: float = 2.0, blur: float = 0.6, supersample: int = 3,
                     plane_z_mm: float = 0.0, aruco_dictionary: str | None = None,
                     seed: int = 0) -> np.ndarray:
    """Photograph a bare bed with white dot markers through ``camera``.

    Parameters
    ----------
    camera : CameraModel
        With pose; photo size is ``camera.image_size``; distortion is applied.
    markers_mm : ndarray, shape (n, 2)
        Marker centres on the bed, mm.
    marker_diameter_mm : float
        Dot diameter, mm.
    bed_rgb, marker_rgb, background_rgb : tuple of int
        Colours (RGB) of the bed, dots, and whatever lies beyond the bed.
    texture : {"plain", "pei", "grid"}
        Bed surface: flat, grainy (textured PEI), or a 10 mm grid.
    bed_extent_mm : float
        Side of the (square) bed plate, mm, centred on ``bed_center_mm``
        (default: the markers' centroid).
    px_per_mm : float
        Resolution of the bed texture.
    glare : float
        Strength (0..1) of a broad specular highlight across the bed.
    exposure : float
        Gain on all intensities (> 1 saturates highlights).
    noise, blur : float
        Gaussian sensor noise sigma (grey levels) and blur sigma (px).
    supersample : int
        Rays per pixel along each axis.
    plane_z_mm : float
        Height of the textured plane (tests of the per-layer warp), mm.
    aruco_dictionary : str or None
        Draw ArUco tags (id ``i`` at ``markers_mm[i]``, side
        ``marker_diameter_mm``, white quiet zone) instead of dots.
    seed : int
        Seed of texture grain and noise.

    Returns
    -------
    ndarray, uint8, shape (h, w, 3)
        BGR photo.
    """
    rng = np.random.default_rng(seed)
    markers = np.asarray(markers_mm, float).reshape(-1, 2)
    center = np.asarray(bed_center_mm if bed_center_mm is not None
                        else (markers.mean(0) if len(markers) else (0.0, 0.0)), float)
    dots = markers if aruco_dictionary is None else np.empty((0, 2))
    tex, A = _bed_texture(center, bed_extent_mm, px_per_mm, bed_rgb, texture, dots,
                          marker_diameter_mm / 2.0, marker_rgb, rng)
    if aruco_dictionary is not None:
        _draw_aruco(tex, A, markers, marker_diameter_mm, px_per_mm, aruco_dictionary)
    img = render_plane(camera, tex, A, z_mm=plane_z_mm, background_rgb=background_rgb, supersample=supersample)
    h, w = img.shape[:2]
    if glare > 0:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        gx, gy = rng.uniform(0.3, 0.7) * w, rng.uniform(0.35, 0.6) * h
        g = np.exp(-(((xx - gx) / (0.18 * w)) ** 2 + ((yy - gy) / (0.10 * h)) ** 2))
        img += (255.0 * glare * g)[..., None]
    img *= float(exposure)
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), float(blur))
    if noise > 0:
        img += rng.normal(0, float(noise), img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def chessboard_texture(cols: int, rows: int, square_mm: float, px_per_mm: float = 10.0,
                       border_squares: float = 1.0):
    """Texture of a chessboard with ``cols x rows`` inner corners; returns ``(texture, texture_from_plane, corners_mm)``.

    Board coordinates: inner corner ``(i, j)`` at ``(i * square, j * square, 0)``
    mm, ``i`` along x; ``corners_mm`` has shape ``(rows * cols, 3)`` in
    OpenCV's row-major order.
    """
    nsx, nsy = cols + 1, rows + 1
    b = border_squares * square_mm
    wmm, hmm = nsx * square_mm + 2 * b, nsy * square_mm + 2 * b
    tw, th = int(round(wmm * px_per_mm)), int(round(hmm * px_per_mm))
    yy, xx = np.mgrid[0:th, 0:tw].astype(np.float64)
    # texture px -> board mm (y down in texture = +y of the board)
    X = (xx + 0.5) / px_per_mm - b - square_mm
    Y = (yy + 0.5) / px_per_mm - b - square_mm
    ix, iy = np.floor(X / square_mm + 1), np.floor(Y / square_mm + 1)
    inside = (ix >= 0) & (ix < nsx) & (iy >= 0) & (iy < nsy)
    black = inside & ((ix + iy) % 2 == 0)
    tex = np.where(black, 20, 235).astype(np.float32)[..., None].repeat(3, -1)
    A = np.array([[px_per_mm, 0, (b + square_mm) * px_per_mm - 0.5],
                  [0, px_per_mm, (b + square_mm) * px_per_mm - 0.5], [0, 0, 1.0]])
    j, i = np.mgrid[0:rows, 0:cols]
    corners = np.stack([i.ravel() * square_mm, j.ravel() * square_mm, np.zeros(i.size)], -1)
    return tex, A, corners
