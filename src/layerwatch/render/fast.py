"""Fast CPU reference renderer: the ideal layer seen from above, in milliseconds.

Every extrusion segment of layers ``0..n`` becomes a bead (capsule of the
segment's width with a rounded top of the layer's height) in a height map
(z-buffer, max per pixel). The height map is shaded from its normals under a
ring light (paper) or a directional light, so bead edges produce the
gradients HOG looks at and the infill direction is visible; lower layers
seen through gaps darken with depth and the bare bed shows the bed colour
(and optional white markers).

Layers are accumulated incrementally: :class:`StackRenderer` keeps the
height map of the layers already drawn, so rendering a job layer by layer
rasterises every segment once. :func:`render_layer` reuses the last
renderer of the same toolpath when called with increasing indices.

References
----------
Petsiuk & Pearce (2022), Section 2.4 (reference images from G-code, ring
light), Fig. 4.
"""

from __future__ import annotations

import logging
import threading
import weakref
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from layerwatch.errors import RenderError
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.render.camera_image import CameraImageRays
from layerwatch.render.camera_view import WallLook, view_from_camera
from layerwatch.render.raster import (
    directional_light,
    raster_capsules,
    ring_lights,
    shade_height,
)
from layerwatch.render.settings import RenderSettings
from layerwatch.render.volume import OccupancyStack, view_through_volume

__all__ = ["Rendered", "StackRenderer", "render_layer", "render_stack", "segment_pixels"]

log = logging.getLogger(__name__)

_GREY = np.array([0.299, 0.587, 0.114])
#: largest occupancy volume (``render.reference = "volume"``) a renderer keeps; beyond it the height map is used
VOLUME_MAX_BYTES = 512 * 2**20


@dataclass
class Rendered:
    """A rendered reference of one layer.

    Attributes
    ----------
    image : ndarray, shape (H, W), uint8
        Grey reference image (top view).
    height : ndarray, shape (H, W), float32
        Height of the printed surface, mm (0 = bare bed).
    mask : ndarray, shape (H, W), bool
        Footprint of layer ``layer`` alone (union of its bead capsules).
    layer : int
        Layer index.
    z : float
        Top of the layer, mm.
    light : ndarray, shape (H, W), float32
        Light factor in [0, 1] (shading times depth darkening) of the scene
        seen from straight above; a camera-view ``image`` is resampled from
        this shading along the camera's rays, so ``light`` (and :meth:`rgb`)
        stay the top-view rendering of the same scene.
    clipped : int
        Segments of the layer (partly) outside the observed square.
    registration : ndarray, shape (H, W), uint8, or None
        The same view rendered with ``registration_darkening`` as its depth darkening
        (:class:`~layerwatch.render.settings.RenderSettings`): what the registrations read;
        ``None``: they read ``image`` (no such setting, or the same darkening).
    """

    image: np.ndarray
    height: np.ndarray
    mask: np.ndarray
    layer: int
    z: float
    light: np.ndarray
    clipped: int = 0
    registration: np.ndarray | None = None

    @property
    def registered(self) -> np.ndarray:
        """The grey reference the registrations read: :attr:`registration`, else :attr:`image`."""
        return self.image if self.registration is None else self.registration

    def rgb(self, settings: RenderSettings | None = None) -> np.ndarray:
        """Colour top view of the scene, shape (H, W, 3), uint8 RGB, from the material/bed colours.

        Always the view from straight above (``light``), also when ``image``
        is the camera-view reference.
        """
        s = settings or RenderSettings()
        albedo = np.where(
            (self.height > 0)[..., None],
            np.asarray(s.material_rgb, np.float32),
            np.asarray(s.bed_rgb, np.float32),
        )
        return np.clip(albedo * self.light[..., None] * 255.0 + 0.5, 0, 255).astype(np.uint8)


def segment_pixels(toolpath: Toolpath, sl: slice, topview: TopView):
    """Pixel endpoints and radii of the segments in ``sl``.

    Returns
    -------
    p0, p1 : ndarray, shape (S, 2), float64
        Endpoints ``(u, v)`` in top-view pixels.
    r : ndarray, shape (S,), float64
        Bead half-width in pixels.
    """
    p0 = topview.to_px(toolpath.start[sl])
    p1 = topview.to_px(toolpath.end[sl])
    r = np.asarray(toolpath.width[sl], np.float64) * (0.5 * topview.px_per_mm)
    return np.ascontiguousarray(p0), np.ascontiguousarray(p1), np.ascontiguousarray(r)


def _check_index(toolpath: Toolpath, index: int) -> int:
    n = toolpath.n_layers
    if n == 0:
        raise RenderError(f"{toolpath.source} has no layers to render; check the G-code has extrusion moves.")
    if not -n <= index < n:
        raise RenderError(f"layer {index} does not exist in {toolpath.source} (0..{n - 1}); pick a layer in range.")
    return index % n


class StackRenderer:
    """Incremental renderer: keeps the height map of the layers drawn so far.

    Parameters
    ----------
    toolpath : Toolpath
    topview : TopView
    settings : RenderSettings, optional
    camera : CameraModel, optional
        The posed camera whose view :meth:`render` draws (``camera_center_mm`` its centre). Given,
        with ``settings.reference = "volume"`` and ``settings.march = "image"``, the volume is
        marched once per camera pixel and kept, each layer adding only what it changed
        (:mod:`layerwatch.render.camera_image`); otherwise every layer's plane is marched anew.
    """

    def __init__(self, toolpath: Toolpath, topview: TopView, settings: RenderSettings | None = None,
                 camera: CameraModel | None = None):
        self.toolpath = toolpath
        self.topview = topview
        self.settings = settings or RenderSettings()
        s = self.settings
        self._lights = (
            ring_lights(s.light_elevation_deg)
            if s.light == "ring"
            else directional_light(s.light_azimuth_deg, s.light_elevation_deg)
        )
        self._mat = float(np.asarray(s.material_rgb) @ _GREY)
        #: occupancy of the printed layers (``reference = "volume"``), else ``None``
        self.volume = None
        if s.reference == "volume":
            lays = toolpath.layers
            self.volume = OccupancyStack(topview.shape, [la.z for la in lays], [la.height for la in lays],
                                         s.volume_fill_layers)
            if self.volume.max_nbytes > VOLUME_MAX_BYTES:
                log.warning("the occupancy volume of %d layers at %dx%d px would take %.0f MB: using the height "
                            "map reference (lower topview.px_per_mm to use the volume)", len(self.volume.tops),
                            topview.shape[1], topview.shape[0], self.volume.max_nbytes / 1e6)
                self.volume = None
        #: the camera-image rays (``march = "image"``), else ``None``
        self.rays: CameraImageRays | None = None
        if self.volume is not None and s.march == "image" and camera is not None and camera.has_pose:
            self.rays = _camera_rays(toolpath, topview, camera)
        self.reset()

    def reset(self) -> None:
        """Forget the accumulated layers."""
        #: the height map between renders, on :attr:`_hbox` (rows r0:r1, columns c0:c1) only: nothing is
        #: printed elsewhere (0 there), so a printer holds the part's box, not the whole view
        self._held = np.zeros((0, 0), np.float32)
        self._hbox = (0, 0, 0, 0)
        self._work: np.ndarray | None = None  # the whole height map while a render runs
        self.done = -1  # last layer rasterised into the height map
        if self.volume is not None:
            self.volume.reset()
        if self.rays is not None:
            self.rays.reset()
        #: changes rasterised but not yet given to the camera-image rays (:meth:`_rays_flush`)
        self._pending: list[tuple[list[tuple[int, int, int, int, float]], float]] = []

    @property
    def height(self) -> np.ndarray:
        """Height map of the layers drawn so far, float32 (H, W), mm (0 = bare bed).

        Between renders it is rebuilt from the printed box (a new array each time: read it, don't write it).
        """
        if self._work is not None:
            return self._work
        full = np.zeros(self.topview.shape, np.float32)
        r0, r1, c0, c1 = self._hbox
        full[r0:r1, c0:c1] = self._held
        return full

    def _cover(self, p0: np.ndarray, p1: np.ndarray, r: np.ndarray) -> None:
        """Grow :attr:`_hbox` to take every pixel :func:`raster_capsules` can write for these capsules (and 1 px)."""
        if p0.shape[0] == 0:
            return
        u0, u1, v0, v1 = _capsule_box(p0, p1, r, self.topview.shape)
        r0, r1, c0, c1 = self._hbox
        if r1 > r0 and c1 > c0:
            v0, v1, u0, u1 = min(v0, r0), max(v1, r1), min(u0, c0), max(u1, c1)
        self._hbox = (v0, v1, u0, u1)

    @property
    def _bed(self) -> np.ndarray:
        """Bed albedo of the top view, float32 (H, W): drawn per render (~0.1 ms) rather than held (1.4 MB at
        600 x 600 px, per printer in a farm)."""
        return self._bed_albedo()

    def _bed_albedo(self) -> np.ndarray:
        s = self.settings
        bed = np.full(self.topview.shape, float(np.asarray(s.bed_rgb) @ _GREY), np.float32)
        if s.markers_mm:
            r = max(int(round(0.5 * s.marker_diameter_mm * self.topview.px_per_mm * 16)), 1)
            for uv in self.topview.to_px(np.asarray(s.markers_mm, np.float64)):
                c = (int(round(uv[0] * 16)), int(round(uv[1] * 16)))
                cv2.circle(bed, c, r, 0.95, -1, cv2.LINE_AA, shift=4)
        return bed

    def _raster(self, index: int, mask: np.ndarray | None) -> int:
        """Add layer ``index`` to the height map and write its footprint into ``mask``."""
        tp = self.toolpath
        layer = tp.layers[index]
        if layer.n_segments == 0:
            return 0
        sl = tp.layer_slice(index)
        p0, p1, r = segment_pixels(tp, sl, self.topview)
        h = layer.height if layer.height > 0 and np.isfinite(layer.height) else 0.2
        hh = np.full(p0.shape[0], min(h, 2.0), np.float64)
        ztop = np.ascontiguousarray(tp.z[sl], np.float64)
        if mask is None and self.volume is not None:  # the volume needs every layer's footprint
            mask = np.zeros(self.topview.shape, bool)
        m = np.zeros((1, 1), bool) if mask is None else mask
        self._cover(p0, p1, r)
        box = _capsule_box(p0, p1, r, self.topview.shape) if self.rays is not None else None
        old = None if box is None else self.height[box[2]:box[3], box[0]:box[1]].copy()
        clipped = raster_capsules(self.height, m, p0, p1, r, ztop, hh, True, mask is not None)
        lowest = self.volume.add(index, m) if self.volume is not None else None
        if box is not None and old is not None:
            self._rays_add(box, old, m, lowest, h)
        return clipped

    def _rays_add(self, box: tuple[int, int, int, int], old: np.ndarray, mask: np.ndarray, lowest: int | None,
                  lh: float) -> None:
        """Give the camera-image rays what a layer of thickness ``lh`` changed in ``box`` (its heights before:
        ``old``; ``lowest``: the lowest slot the occupancy may have changed in, ``None``: none).

        A point became solid only in a pixel whose height or occupancy changed, above its old height or above
        the floor of the lowest changed slot: the changed pixels are split into those where that bound lies
        within two layers of the new top (most of a layer: a short segment of each ray) and the rest.
        """
        assert self.rays is not None and self.volume is not None
        u0, u1, v0, v1 = box
        new = self.height[v0:v1, u0:u1]
        changed = (new != old) | mask[v0:v1, u0:u1]
        if not changed.any():
            return
        vol = self.volume
        floor = (float(vol.tops[lowest - 1]) if lowest > 0 else -1e9) if lowest is not None else np.inf
        deep = np.where(changed, np.minimum(old, np.float32(floor)), np.inf)
        zhi = float(new[changed].max())
        split = zhi - 2.0 * lh
        shallow = changed & (deep >= split)
        deeper = changed & ~shallow
        boxes = []
        for part, zlo in ((shallow, split), (deeper, float(deep[deeper].min()) if deeper.any() else 0.0)):
            if part.any():
                rows, cols = np.flatnonzero(part.any(axis=1)), np.flatnonzero(part.any(axis=0))
                boxes.append((u0 + int(cols[0]), u0 + int(cols[-1]) + 1, v0 + int(rows[0]), v0 + int(rows[-1]) + 1, zlo))
        self._pending.append((boxes, zhi))

    def _rays_flush(self) -> None:
        """Hand the layers rasterised since the last render to the camera-image rays in one pass.

        One layer: its own boxes. Several (a render that catches up, e.g. after a reset): their union with
        the lowest bound, so that each ray is looked at once, not once per layer (points only ever
        become solid, so one pass over the union finds the same first hits).
        """
        pending, self._pending = self._pending, []
        if self.rays is None or self.volume is None or not pending:
            return
        if len(pending) == 1:
            boxes, zhi = pending[0]
        else:
            every = [b for bs, _ in pending for b in bs]
            boxes = [(min(b[0] for b in every), max(b[1] for b in every), min(b[2] for b in every),
                      max(b[3] for b in every), min(b[4] for b in every))] if every else []
            zhi = max(z for _, z in pending)
        self.rays.add(self.height, self.volume, boxes, zhi)

    def render(self, index: int, camera_center_mm: np.ndarray | None = None) -> Rendered:
        """Render layer ``index`` (all layers ``0..index``), reusing earlier work.

        Parameters
        ----------
        index : int
        camera_center_mm : ndarray, shape (3,), optional
            Camera centre in bed mm. Given, the image is the scene as that
            camera sees it through the layer's plane
            (:func:`~layerwatch.render.camera_view.view_from_camera`: walls,
            parallax of lower layers); omitted, the orthographic top view.

        Raises
        ------
        RenderError
            The toolpath has no layers or ``index`` is out of range.
        """
        tp = self.toolpath
        index = _check_index(tp, index)
        if index < self.done:
            self.reset()
        self._work = self.height  # the whole map for this render; only its printed box is kept after it
        try:
            return self._render(index, camera_center_mm)
        finally:
            r0, r1, c0, c1 = self._hbox
            self._held, self._work = self._work[r0:r1, c0:c1].copy(), None

    def _render(self, index: int, camera_center_mm: np.ndarray | None) -> Rendered:
        tp = self.toolpath
        for i in range(self.done + 1, index):
            self._raster_height_only(i)
        mask = np.zeros(self.topview.shape, bool)
        layer = tp.layers[index]
        if index == self.done:  # already in the height map: footprint only
            clipped = self._mask_only(index, mask)
        else:
            clipped = self._raster(index, mask)
            self.done = index
        if clipped:
            log.warning(
                "layer %d: %d segments reach outside the observed square and are clipped",
                index, clipped,
            )
        self._rays_flush()
        return self._shade(index, layer.z, layer.height, mask, clipped, camera_center_mm)

    def _raster_height_only(self, i: int) -> None:
        self._raster(i, None)
        self.done = i

    def _mask_only(self, index: int, mask: np.ndarray) -> int:
        tp = self.toolpath
        if tp.layers[index].n_segments == 0:
            return 0
        p0, p1, r = segment_pixels(tp, tp.layer_slice(index), self.topview)
        dummy = np.zeros(p0.shape[0], np.float64)
        return raster_capsules(self.height, mask, p0, p1, r, dummy, dummy, False, True)

    def _shade_box(self) -> tuple[int, int, int, int] | None:
        """Rows and columns ``(r0, r1, c0, c1)`` outside which the light is the bare bed's (``None``: the whole view).

        The printed box grown by the reach of the height map's smoothing, the shading's gradient and the
        cavity's dilation: beyond it the smoothed surface and its neighbours are 0 (OpenCV's Gaussian
        kernel has a radius of ``round(4 sigma)`` for float images), so every pixel is lit as a level bed.
        """
        r0, r1, c0, c1 = self._hbox
        if r1 <= r0 or c1 <= c0:
            return None
        reach = self._light_reach()
        H, W = self.topview.shape
        box = (max(r0 - reach, 0), min(r1 + reach, H), max(c0 - reach, 0), min(c1 + reach, W))
        return None if box == (0, H, 0, W) else box

    def _light_reach(self) -> int:
        """How far (px) a height reaches into the light: smoothing (``round(4 sigma)``), gradient and cavity, with 1 px spare."""
        s = self.settings
        reach = (int(np.ceil(4 * s.smooth_px)) + 1 if s.smooth_px > 0 else 0) + 2
        if s.cavity > 0:
            reach += int(np.ceil(s.cavity_radius_mm * self.topview.px_per_mm)) + 1
        return reach

    def _light(self, z: float, lh: float, box: tuple[int, int, int, int] | None,
               depth_darkening: float | None = None) -> np.ndarray:
        """Light factor of the top view (float32 (H, W), 0-1): shading, depth darkening and cavities.

        With ``box`` (:meth:`_shade_box`) it is computed on the box grown by its own reach (so that every
        value in the box reads the same neighbours as on the whole view) and the rest is the level bed's
        light: the same values as on the whole view, float for float (``tests/render/test_camera_image.py``).
        ``depth_darkening``: the settings' unless given.
        """
        s = self.settings
        H, W = self.topview.shape
        if box is None:
            g, inner = (0, H, 0, W), (slice(0, H), slice(0, W))
        else:
            r0, r1, c0, c1 = box
            m = self._light_reach()
            g = (max(r0 - m, 0), min(r1 + m, H), max(c0 - m, 0), min(c1 + m, W))
            inner = (slice(r0 - g[0], r1 - g[0]), slice(c0 - g[2], c1 - g[2]))
        height = self.height[g[0]:g[1], g[2]:g[3]]
        part = np.empty(height.shape, np.float32)
        surf: np.ndarray = height
        if s.smooth_px > 0:
            surf = cv2.GaussianBlur(surf, (0, 0), s.smooth_px, borderType=cv2.BORDER_REPLICATE)
        dark = s.depth_darkening if depth_darkening is None else float(depth_darkening)
        args = (z, self.topview.px_per_mm * s.relief, self._lights, s.ambient, s.layers_visible_below * lh, dark)
        shade_height(surf, *args, part)
        if s.cavity > 0:
            # ambient occlusion of valleys: how far a pixel lies below its neighbourhood
            k = 2 * int(np.ceil(s.cavity_radius_mm * self.topview.px_per_mm)) + 1
            top = cv2.dilate(height, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
            occl = np.minimum((top - height) * np.float32(1.0 / lh), 1.0)
            part *= 1.0 - np.float32(s.cavity) * occl
        if box is None:
            return part
        level = np.empty((3, 3), np.float32)
        shade_height(np.zeros((3, 3), np.float32), *args, level)
        light = np.full((H, W), level[1, 1], np.float32)
        light[box[0]:box[1], box[2]:box[3]] = part[inner]
        return light

    def _shade(self, index: int, z: float, lh: float, mask: np.ndarray, clipped: int,
               camera_center_mm: np.ndarray | None = None) -> Rendered:
        s = self.settings
        lh = lh if lh > 0 and np.isfinite(lh) else 0.2
        box = self._shade_box()
        light = self._light(z, lh, box)
        albedo = np.where(self.height > 0, np.float32(self._mat), self._bed)
        image = self._image(albedo * light, camera_center_mm, z, lh, s.depth_darkening)
        reg = s.registration_darkening
        registration = (None if reg is None or reg == s.depth_darkening
                        else self._image(albedo * self._light(z, lh, box, reg), camera_center_mm, z, lh, reg))
        return Rendered(image, self.height, mask, index, float(z), light, int(clipped),  # (the render's own map)
                        registration)

    def _image(self, img: np.ndarray, camera_center_mm: np.ndarray | None, z: float, lh: float,
               depth_darkening: float) -> np.ndarray:
        """The grey reference, uint8 (H, W), from the shaded top view ``img`` (albedo x light, float32 (H, W)):
        seen by the camera (``camera_center_mm``; hidden tops darkened by ``depth_darkening``), blurred."""
        s = self.settings
        if camera_center_mm is not None:
            img = self._camera_view(img, camera_center_mm, z, lh, depth_darkening)
        if s.image_blur_px > 0:  # optics: the camera never resolves a bead edge as a step
            img = cv2.GaussianBlur(img, (0, 0), s.image_blur_px, borderType=cv2.BORDER_REPLICATE)
        return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)

    def _camera_view(self, img: np.ndarray, center_mm: np.ndarray, z: float, lh: float,
                     depth_darkening: float) -> np.ndarray:
        """The shaded top view ``img`` as the camera at ``center_mm`` sees it through the plane ``Z = z``
        (a top hidden under something higher darkened by ``depth_darkening`` at the settings' depth)."""
        s = self.settings
        look = WallLook(layer_height_mm=lh, wall_value=s.wall_light * self._mat,
                        wall_line_contrast=s.wall_line_contrast, wall_ambient=s.wall_ambient)
        if self.volume is None:
            return view_from_camera(self.height, img, center_mm, self.topview, z, look=look)[0]
        if self.rays is not None:
            shading = np.array([look.wall_value, look.wall_ambient, look.wall_line_contrast, look.layer_height_mm,
                                self._mat, s.layers_visible_below * lh, depth_darkening], np.float64)
            return self.rays.view(self.height, img, self._bed, self.volume, z, shading)
        return view_through_volume(
            self.height, img, self.volume, self._bed, center_mm, self.topview, z, look=look, hidden_value=self._mat,
            depth_scale_mm=s.layers_visible_below * lh, depth_darkening=depth_darkening, printed_box=self._hbox,
        )[0]


def _capsule_box(p0: np.ndarray, p1: np.ndarray, r: np.ndarray, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(u0, u1, v0, v1)``: top-view columns and rows (half-open) :func:`raster_capsules` can write (and 1 px)."""
    H, W = shape
    if p0.shape[0] == 0:
        return 0, 0, 0, 0
    v0 = int(np.ceil(np.minimum(p0[:, 1], p1[:, 1]) - r).min()) - 1
    v1 = int(np.floor(np.maximum(p0[:, 1], p1[:, 1]) + r).max()) + 2
    u0 = int(np.ceil(np.minimum(p0[:, 0], p1[:, 0]) - r).min()) - 1
    u1 = int(np.floor(np.maximum(p0[:, 0], p1[:, 0]) + r).max()) + 2
    return min(max(u0, 0), W), min(max(u1, 0), W), min(max(v0, 0), H), min(max(v1, 0), H)


def _camera_rays(toolpath: Toolpath, topview: TopView, camera: CameraModel) -> CameraImageRays | None:
    """The camera-image rays of a print: the grid over what the print's box projects to (``None``: nothing printed)."""
    if toolpath.n_layers == 0 or len(toolpath.start) == 0:
        return None
    p0, p1, r = segment_pixels(toolpath, slice(0, len(toolpath.start)), topview)
    box = _capsule_box(p0, p1, r, topview.shape)
    if box[1] <= box[0] or box[3] <= box[2]:
        return None
    hs = np.asarray([la.height for la in toolpath.layers], np.float64)
    hs = hs[np.isfinite(hs) & (hs > 0)]
    zs = np.asarray([la.z for la in toolpath.layers], np.float64)
    return CameraImageRays(camera, topview, box, float(np.nanmax(zs)), float(hs.min()) if hs.size else 0.2)


_LAST: dict[str, object] = {}  # the most recent renderer (holds one toolpath alive)
_LOCK = threading.Lock()


def render_layer(
    toolpath: Toolpath,
    index: int,
    topview: TopView,
    settings: RenderSettings | None = None,
) -> Rendered:
    """Render the reference of layer ``index``: all layers ``0..index`` seen from above.

    Consecutive calls on the same toolpath, top view and settings with
    non-decreasing ``index`` continue from the previous height map.

    Parameters
    ----------
    toolpath : Toolpath
    index : int
        Layer index (negative counts from the end).
    topview : TopView
        Scale and observed square; segments outside it are clipped (logged).
    settings : RenderSettings, optional

    Returns
    -------
    Rendered
        ``image`` uint8 (H, W), ``height`` float32 (H, W) mm, ``mask`` bool (H, W).

    References
    ----------
    Petsiuk & Pearce (2022), Section 2.4.
    """
    settings = settings or RenderSettings()
    key = (topview, settings.model_dump_json())
    with _LOCK:
        ref = _LAST.get("toolpath")
        renderer = _LAST.get("renderer")
        if (not isinstance(ref, weakref.ref) or ref() is not toolpath or _LAST.get("key") != key
                or not isinstance(renderer, StackRenderer)):
            renderer = StackRenderer(toolpath, topview, settings)
            _LAST.update(toolpath=weakref.ref(toolpath), key=key, renderer=renderer)
        return renderer.render(index)


def render_stack(
    toolpath: Toolpath,
    topview: TopView,
    settings: RenderSettings | None = None,
    layers: Iterable[int] | None = None,
) -> Iterator[Rendered]:
    """Render several layers in increasing order, rasterising each segment once.

    Parameters
    ----------
    layers : iterable of int, optional
        Layer indices (sorted internally); all layers when omitted.

    Yields
    ------
    Rendered
        One per requested layer, in increasing layer order.
    """
    renderer = StackRenderer(toolpath, topview, settings)
    idx = range(toolpath.n_layers) if layers is None else sorted({int(i) for i in layers})
    for i in idx:
        yield renderer.render(i)
