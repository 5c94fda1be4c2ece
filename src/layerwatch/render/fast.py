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
from layerwatch.geometry.topview import TopView
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
    """

    image: np.ndarray
    height: np.ndarray
    mask: np.ndarray
    layer: int
    z: float
    light: np.ndarray
    clipped: int = 0

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
    """

    def __init__(self, toolpath: Toolpath, topview: TopView, settings: RenderSettings | None = None):
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
        self.reset()

    def reset(self) -> None:
        """Forget the accumulated layers."""
        self.height = np.zeros(self.topview.shape, np.float32)
        self.done = -1  # last layer rasterised into self.height
        if self.volume is not None:
            self.volume.reset()

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
        clipped = raster_capsules(self.height, m, p0, p1, r, ztop, hh, True, mask is not None)
        if self.volume is not None:
            self.volume.add(index, m)
        return clipped

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

    def _shade(self, index: int, z: float, lh: float, mask: np.ndarray, clipped: int,
               camera_center_mm: np.ndarray | None = None) -> Rendered:
        s = self.settings
        lh = lh if lh > 0 and np.isfinite(lh) else 0.2
        light = np.empty(self.topview.shape, np.float32)
        surf: np.ndarray = self.height
        if s.smooth_px > 0:
            surf = cv2.GaussianBlur(surf, (0, 0), s.smooth_px, borderType=cv2.BORDER_REPLICATE)
        shade_height(
            surf,
            z,
            self.topview.px_per_mm * s.relief,
            self._lights,
            s.ambient,
            s.layers_visible_below * lh,
            s.depth_darkening,
            light,
        )
        if s.cavity > 0:
            # ambient occlusion of valleys: how far a pixel lies below its neighbourhood
            k = 2 * int(np.ceil(s.cavity_radius_mm * self.topview.px_per_mm)) + 1
            top = cv2.dilate(self.height, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
            occl = np.minimum((top - self.height) * np.float32(1.0 / lh), 1.0)
            light *= 1.0 - np.float32(s.cavity) * occl
        albedo = np.where(self.height > 0, np.float32(self._mat), self._bed)
        img: np.ndarray = albedo * light
        if camera_center_mm is not None:
            img = self._camera_view(img, camera_center_mm, z, lh)
        if s.image_blur_px > 0:  # optics: the camera never resolves a bead edge as a step
            img = cv2.GaussianBlur(img, (0, 0), s.image_blur_px, borderType=cv2.BORDER_REPLICATE)
        image = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
        return Rendered(image, self.height.copy(), mask, index, float(z), light, int(clipped))


    def _camera_view(self, img: np.ndarray, center_mm: np.ndarray, z: float, lh: float) -> np.ndarray:
        """The shaded top view ``img`` as the camera at ``center_mm`` sees it through the plane ``Z = z``."""
        s = self.settings
        look = WallLook(layer_height_mm=lh, wall_value=s.wall_light * self._mat,
                        wall_line_contrast=s.wall_line_contrast, wall_ambient=s.wall_ambient)
        if self.volume is None:
            return view_from_camera(self.height, img, center_mm, self.topview, z, look=look)[0]
        return view_through_volume(
            self.height, img, self.volume, self._bed, center_mm, self.topview, z, look=look, hidden_value=self._mat,
            depth_scale_mm=s.layers_visible_below * lh, depth_darkening=s.depth_darkening,
        )[0]


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
