"""The virtual camera rig: rays per pixel, lights, bed albedo and the sensor model.

A :class:`Photographer` holds what depends only on the camera and the bed
(ray directions through the lens distortion, the bare bed's albedo seen by
each pixel, vignetting, a noise bank; shared between simulators through a
small cache) and turns a height field into a BGR photo with
:func:`~layerwatch.simulate.shade.render_view` and
:func:`~layerwatch.simulate.shade.finish`.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.simulate.raster import grid_params
from layerwatch.simulate.scene import default_markers
from layerwatch.simulate.settings import SimSettings
from layerwatch.simulate.shade import bed_albedo_image, finish, render_view

__all__ = ["Photographer"]

_CACHE: dict = {}

#: a one-cell pit deeper than this many layers is a slit between two beads, not a slope of their tops
_SLIT_LAYERS = 3.0


def _cached(key, value=None):
    """Tiny cache of per-camera arrays (rays, bed albedo, noise) shared by simulators."""
    if value is None:
        return _CACHE.get(key)
    if len(_CACHE) >= 8:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = value
    return value


class Photographer:
    """Camera, lights and sensor of the simulator.

    Parameters
    ----------
    camera : CameraModel
        Posed camera; ``image_size`` is the photo size.
    topview : TopView
        Its centre is the light's aim; its corners the default markers.
    grid : TopView
        Geometry of the height fields handed to :meth:`shoot`.
    settings : SimSettings
    seed : int
    """

    def __init__(self, camera: CameraModel, topview: TopView, grid: TopView, settings: SimSettings,
                 seed: int) -> None:
        self.camera, self.topview, self.grid = camera, topview, grid
        self.settings, self.seed = settings, int(seed)
        self.gp = grid_params(grid)
        st = settings
        self._rays()
        self.markers = (np.asarray(st.markers_mm, float).reshape(-1, 2) if st.markers_mm
                        else default_markers(topview))
        side = st.bed_size_mm or 2.4 * max(topview.width_mm, topview.height_mm)
        cx, cy = topview.center_mm
        self.bed = np.array([cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2])
        self.albedo = np.array([st.bed_rgb, st.filament_rgb, st.filament_rgb, (0.05, 0.05, 0.06),
                                (0.55, 0.56, 0.6), (0.1, 0.25, 0.75)], np.float64)
        self.spec = np.array([[0.04, 8], [0.25, 30], [0.35, 40], [0.15, 12], [0.9, 60], [0.3, 25]],
                             np.float64)
        w, h = camera.image_size
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        self.vignette = (1 - st.vignetting * r2).astype(np.float32)
        bkey = self._key + ("bed", self.bed.tobytes(), self.markers.tobytes(), st.bed_rgb,
                            st.background_rgb, st.marker_diameter_mm, self.seed)
        self.bed_alb = _cached(bkey) if _cached(bkey) is not None else _cached(bkey, bed_albedo_image(
            self.dirs, self.C, self.bed, np.asarray(st.bed_rgb, float),
            np.asarray(st.background_rgb, float), self.markers, st.marker_diameter_mm / 2, self.seed))
        nkey = ("noise", w, h)
        self.noise_bank = _cached(nkey)
        if self.noise_bank is None:
            nrng = np.random.default_rng(20261123)
            self.noise_bank = _cached(nkey, nrng.standard_normal((h + 32, w + 32, 3), np.float32))
        self.lut = (np.clip(np.linspace(0, 1, 4096), 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)

    def _rays(self) -> None:
        cam = self.camera
        rvec, tvec = cam.pose
        key = ("rays", cam.image_size, cam.K.tobytes(), cam.dist.tobytes(), rvec.tobytes())
        dirs = _cached(key)
        if dirs is None:
            w, h = cam.image_size
            uv = np.stack(np.meshgrid(np.arange(w, dtype=np.float64),
                                      np.arange(h, dtype=np.float64)), -1).reshape(-1, 1, 2)
            n = cv2.undistortPoints(uv, cam.K, cam.dist).reshape(h, w, 2)
            d = np.concatenate([n, np.ones((h, w, 1))], -1)
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            dirs = _cached(key, np.ascontiguousarray((d @ cam.R).astype(np.float32)))
        self.dirs = dirs
        self.C = cam.center_mm.astype(np.float64)
        self._key = key + (tvec.tobytes(),)

    def shoot(self, h: np.ndarray, mat: np.ndarray, index: int, layer_h: float, gap: np.ndarray | None = None):
        """Photo of height field ``h`` (float32 (H, W) mm) with materials ``mat`` (uint8).

        ``gap`` (float32 (H, W, 2)): the empty interval ``(lo, hi)`` mm under
        printed material per cell (windows, overhangs, bridges); ``None``: none.

        Returns ``(photo, info)``: BGR uint8 (h, w, 3) and a dict of the frame's
        light position, exposure and blur.
        """
        rng = np.random.default_rng([self.seed, 2, index])
        light = self.light(rng)
        rad = self.radiance(h, mat, layer_h, gap, light)
        return self.develop(rad, index, rng, light)

    def light(self, rng: np.random.Generator) -> np.ndarray:
        """This frame's lights: ``[Lx, Ly, Lz, ax, ay, az, cos_in, cos_out, I, ambient, fill, dref]``.

        A spot beside the camera (position ``light_offset_mm`` in the camera's axes, jittered by
        ``light_jitter_mm``; axis to the observed square's centre; full inside 30 deg, none beyond
        60 deg; intensity ``I`` at distance ``dref``, bed mm), an ambient and an overhead fill
        (:func:`~layerwatch.simulate.shade.render_view` reads them so).
        """
        st = self.settings
        target = np.array([*self.topview.center_mm, 0.0])
        off = np.asarray(st.light_offset_mm, float)
        R = self.camera.R  # camera axes in bed frame are rows of R
        lpos = self.C + R[0] * off[0] + (-R[1]) * off[2] + R[2] * off[1]
        lpos = lpos + rng.normal(0, st.light_jitter_mm, 3)
        axis = target - lpos
        dref = np.linalg.norm(axis)
        axis /= dref
        inten = st.light_intensity * (1 + rng.normal(0, st.light_intensity_jitter))
        amb = st.ambient * (1 + rng.normal(0, 0.1))
        return np.array([*lpos, *axis, np.cos(np.deg2rad(30)), np.cos(np.deg2rad(60)), inten, amb,
                         st.fill, dref])

    def radiance(self, h: np.ndarray, mat: np.ndarray, layer_h: float, gap: np.ndarray | None,
                 light: np.ndarray) -> np.ndarray:
        """Linear RGB radiance of the scene seen by the camera, float32 (h, w, 3) (before the sensor).

        The height field ray-cast and shaded by :func:`~layerwatch.simulate.shade.render_view`
        (``h``, ``mat``, ``gap`` as :meth:`shoot` takes them; ``light`` from :meth:`light`).
        """
        s = self.gp[0]
        h = fold_ledges(h)
        if gap is None:
            gap = np.zeros((*h.shape, 2), np.float32)
        gy, gx = np.gradient(_slits_filled(h, gap, _SLIT_LAYERS * max(float(layer_h), 0.05)))
        wy, wx = np.gradient(cv2.GaussianBlur(h, (0, 0), 1.5))
        wn = np.ascontiguousarray(np.stack([-wx, wy], -1), dtype=np.float32)
        nz = np.full_like(h, 1.0 / s)
        nrm = np.stack([-gx, gy, nz], -1)
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        small = cv2.resize(h, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
        blur = cv2.resize(cv2.GaussianBlur(small, (0, 0), 0.4 * s), h.shape[::-1])
        ao = np.clip(1.0 - 0.35 * (blur - h), 0.35, 1.0).astype(np.float32)
        bbox, zmax = self.printed_box(h)
        w, hh = self.camera.image_size
        rad = np.empty((hh, w, 3), np.float32)
        render_view(self.dirs, self.C, h, mat, np.ascontiguousarray(gap, np.float32), nrm.astype(np.float32), wn, ao, *self.gp, zmax, bbox,
                    self.albedo, self.spec, light, self.bed_alb,
                    np.asarray(self.settings.background_rgb, float), float(layer_h), rad)
        return rad

    def printed_box(self, h: np.ndarray) -> tuple[np.ndarray, float]:
        """``(xmin, ymin, xmax, ymax)`` bed mm of the cells of ``h`` above the bed, one cell wider, and the
        highest point (mm); zeros and 0 when nothing is printed."""
        rows, cols = np.any(h > 0, 1), np.any(h > 0, 0)
        if not rows.any():
            return np.zeros(4), 0.0
        v0, v1 = np.flatnonzero(rows)[[0, -1]]
        u0, u1 = np.flatnonzero(cols)[[0, -1]]
        (xa, ya), (xb, yb) = self.grid.to_mm(np.array([[u0 - 1, v1 + 1], [u1 + 1, v0 - 1]]))
        return np.array([xa, ya, xb, yb]), float(h.max())

    def develop(self, rad: np.ndarray, index: int, rng: np.random.Generator,
                light: np.ndarray) -> tuple[np.ndarray, dict]:
        """The sensor: exposure and white-balance drift, vignetting, blur, noise, gamma; ``(photo, info)``.

        ``rad``: linear RGB radiance (h, w, 3) float32 (:meth:`radiance`); ``rng``: the frame's
        generator after :meth:`light` drew from it.
        """
        st = self.settings
        w, hh = self.camera.image_size
        ph = np.random.default_rng([self.seed, 3]).uniform(0, 2 * np.pi, 4)
        expo = st.exposure * (1 + st.exposure_drift * np.sin(2 * np.pi * index / 37 + ph[0])
                              + rng.normal(0, st.exposure_drift / 3))
        wb = 1 + st.colour_drift * np.sin(2 * np.pi * index / 53 + ph[1:]) + rng.normal(0, 0.01, 3)
        gain = (expo * wb * np.asarray(st.white_balance, float)).astype(np.float32)
        sigma = float(rng.uniform(*st.blur_px))
        img = cv2.GaussianBlur(rad, (0, 0), sigma)
        oy, ox = (int(v) for v in rng.integers(0, 32, 2))
        photo = np.empty((hh, w, 3), np.uint8)
        finish(img, self.vignette, gain.astype(np.float64), self.noise_bank, oy, ox,
               st.read_noise, st.shot_noise, self.lut, photo)
        info = {"light_mm": light[:3].round(1).tolist(), "exposure": float(expo), "blur_px": sigma}
        return photo, info


def fold_ledges(h: np.ndarray) -> np.ndarray:
    """``h`` with one-cell ledges of lower layers under a tall wall raised into the wall.

    The grid quantises the beads' jitter: a cell of a lower layer pokes out under a wall more than
    1 mm tall here and there, and would be drawn as a dark stripe down the wall. float32 (H, W) mm.
    """
    k3 = np.ones((3, 3), np.uint8)
    mx, mn = cv2.dilate(h, k3), cv2.erode(h, k3)
    return np.where((mx - h > 1.0) & (h - mn > 0.1), mx, h)


def _slits_filled(h: np.ndarray, gap: np.ndarray, depth_mm: float) -> np.ndarray:
    """``h`` with one-cell slits between beads printed over air filled, for the top surfaces' normals only.

    Two beads of a layer printed over air (a bridge's deck, an overhang) touch
    with sub-cell gaps from their width and position jitter; where such a gap
    happens to hold a cell centre, the height field has a one-cell slit down
    to whatever lies below (8 mm of air under a bridge). Central differences
    across that slit tilted the tops of both neighbouring beads by ~85 degrees,
    so a hairline gap was drawn as a dark dash three cells (0.4 mm) wide and
    millimetres long, whose darkness grew with the depth below it. A bead's top
    is sloped by its own profile, not by how deep the air beside it is: the
    normals are taken as if the slit were filled. The slit itself stays in the
    geometry (rays still pass into it). Only slits beside cells printed over
    air (``gap``) are filled: pits no deeper than ``depth_mm`` (the grooves
    between beads on a layer below), wider openings and the cavities of
    supported sparse infill are unchanged (a part without bridges or overhangs
    is photographed as before).

    Parameters
    ----------
    h : ndarray, float32, shape (H, W)
        Height field, mm.
    gap : ndarray, float32, shape (H, W, 2)
        Per cell the empty interval ``(lo, hi)`` mm under printed material (``hi = 0``: none).
    depth_mm : float
        Depth below the morphological closing (1x3 or 3x1) above which a cell is a slit.

    Returns
    -------
    ndarray, float32, shape (H, W)
    """
    closed = np.maximum(cv2.morphologyEx(h, cv2.MORPH_CLOSE, np.ones((1, 3), np.uint8)),
                        cv2.morphologyEx(h, cv2.MORPH_CLOSE, np.ones((3, 1), np.uint8)))
    slit = closed - h > depth_mm
    if not slit.any():
        return h
    slit &= cv2.dilate((gap[..., 1] > 0).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return np.where(slit, closed, h)
