"""Reference-rendering settings (config section ``[render]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from layerwatch.settings_base import Section

__all__ = ["RenderSettings"]


class RenderSettings(Section):
    """How the reference of a layer is rendered.

    Attributes
    ----------
    backend : {"fast", "blender"}
        CPU rasteriser (default) or Blender Cycles through the ``blender`` executable.
    view : {"camera", "top"}
        ``"camera"``: where the job has a posed camera, the reference is the
        scene as that camera sees it through the layer's plane (walls facing
        the camera, parallax of lower layers; :mod:`layerwatch.render.camera_view`),
        i.e. what the warped photo shows; ``"top"``: the orthographic top view.
    reference : {"height", "volume"}
        What the camera view is rendered from. ``"height"``: a height map of
        the printed layers (one surface per pixel: everything under a bead is
        solid down to the bed); ``"volume"``: a layer-stack occupancy volume
        (:mod:`layerwatch.render.volume`), so windows through walls,
        cross-holes, overhangs and bridges appear as the camera sees them.
        The two are identical on parts without such features; no effect with
        ``view = "top"`` or the Blender backend. Default ``"volume"``: on clean
        prints of a part with a window, a bridge and an overhang it lowered
        single-layer alarms (13 -> 11 of 210 layers; 139 -> 104 with a 5 mm
        footprint margin; 19 -> 13 of 240 on a sliced 3DBenchy), left the
        example part's a% unchanged, and costs
        ~1.06x the height map's time (``docs/evaluation/volume.md``,
        ``benchmarks/bench_volume.py``). Beyond 512 MB of occupancy the height
        map is used (logged).
    march : {"plane", "image"}
        How the volume (``reference = "volume"``, ``view = "camera"``) is ray-marched.
        ``"plane"``: every layer, the ray through every top-view pixel of that layer's
        plane (:func:`~layerwatch.render.volume.view_through_volume`); ``"image"``: the
        rays of a fixed grid of camera pixels, marched once and kept (2 bytes a ray),
        each layer adding only what it printed, then warped onto the layer's plane
        (:mod:`layerwatch.render.camera_image`; needs the camera model, which the
        pipeline passes). Default ``"plane"``: the kept rays cost about the same per
        layer on the example part (1.09x), half on a part that fills little of the view
        (window part 0.50x), more from scratch and after a reset, and detect neither
        clearly better nor worse (``docs/evaluation/volume.md``).
    volume_fill_layers : int
        ``reference = "volume"``: vertical gaps of up to this many layers
        between printed beads of a pixel are closed (the slit under a sparse
        infill line is not a window).
    material_rgb, bed_rgb : tuple of float
        Linear albedo of the filament and of the bed, each channel in [0, 1].
    light : {"ring", "directional"}
        Ring light around the camera axis (paper) or one directional light.
    light_azimuth_deg, light_elevation_deg : float
        Direction of the directional light (azimuth from +X towards +Y), and
        the elevation of the ring light's rays above the bed.
    ambient : float
        Ambient light fraction added to the diffuse term.
    layers_visible_below : int
        Layers below the current one that stay visible in gaps; they darken
        linearly with depth and anything deeper is shown at the darkest level.
    depth_darkening : float
        Brightness lost at ``layers_visible_below`` layers of depth, in [0, 1].
    registration_darkening : float or None
        ``depth_darkening`` of a second copy of the reference that the registrations read (the residual
        view shift, :mod:`layerwatch.analysis.view_shift`, and the part registration of the failure
        typing, :mod:`layerwatch.analysis.part_registration`), in [0, 1]; ``None``: they read the
        reference itself. The photos light every level surface alike (a lamp far above), so the
        comparison's reference is best photo-like (``depth_darkening = 0``), but the registrations
        correlate the top layer's edges and need the contrast of the lower surfaces below it (floors
        darkened, walls not: only the render knows which is which). The copy costs a second shading
        and camera-view march per layer (the example part's render 19 -> 38 ms a layer at 600 x 600 px)
        and one more grey image per reference (0.36 MB there). Off by default: with
        ``depth_darkening = 0`` and a copy at 0.2 the raster evaluation kept every moved-part figure
        and raised thin-wall AUROC, but two parts' clean prints gained a single-layer alarm each
        (``docs/evaluation/README.md``, "Session 23 (helper light)").
    relief : float
        Exaggeration of the height map's slopes in the shading, so bead
        edges stand out at a few pixels per bead.
    smooth_px : float
        Gaussian sigma (px) applied to the height map before the normals
        are taken (anti-aliasing of the bead profile); 0 disables it.
    cavity, cavity_radius_mm : float
        Ambient occlusion of valleys: brightness lost where the surface lies
        one layer height below the highest point within the radius (gaps
        between beads, lower layers next to walls).
    image_blur_px : float
        Gaussian sigma (px) of the final image (camera optics / warp
        resampling); 0 disables it.
    wall_light : float
        Brightness of a wall facing the camera relative to a lit top surface
        (camera-view references only, see :mod:`layerwatch.render.camera_view`).
    wall_ambient : float
        Share of ``wall_light`` a wall keeps whatever its orientation; the rest
        follows the cosine between its normal and the direction to the camera.
    wall_line_contrast : float
        Depth of the layer lines drawn on such walls, fraction of their brightness.
    markers_mm : list of (x, y) or None
        Bed markers (white dots) drawn on the bed, bed mm; ``None`` draws none.
    marker_diameter_mm : float
        Diameter of the drawn markers, mm.
    blender_samples : int
        Cycles samples per pixel of the Blender backend.
    blender_timeout_s : float
        Seconds after which a Blender render is abandoned (RenderError).
    """

    backend: Literal["fast", "blender"] = "fast"
    view: Literal["camera", "top"] = "camera"
    reference: Literal["height", "volume"] = "volume"
    march: Literal["plane", "image"] = "plane"
    volume_fill_layers: int = Field(2, ge=0, le=20)
    material_rgb: tuple[float, float, float] = (0.85, 0.85, 0.82)
    bed_rgb: tuple[float, float, float] = (0.12, 0.12, 0.13)
    light: Literal["ring", "directional"] = "ring"
    light_azimuth_deg: float = 225.0
    light_elevation_deg: float = 45.0
    ambient: float = Field(0.15, ge=0, le=1)
    layers_visible_below: int = Field(3, ge=0)
    depth_darkening: float = Field(0.2, ge=0, le=1)
    registration_darkening: float | None = Field(None, ge=0, le=1)
    relief: float = Field(1.5, gt=0, le=20)
    smooth_px: float = Field(0.7, ge=0, le=5)
    cavity: float = Field(0.1, ge=0, le=1)
    cavity_radius_mm: float = Field(0.35, gt=0, le=5)
    image_blur_px: float = Field(1.0, ge=0, le=5)
    wall_light: float = Field(0.85, ge=0, le=1)
    wall_ambient: float = Field(1.0, ge=0, le=1)
    wall_line_contrast: float = Field(0.2, ge=0, le=1)
    markers_mm: list[tuple[float, float]] | None = None
    marker_diameter_mm: float = Field(6.0, gt=0)
    blender_samples: int = Field(16, ge=1, le=4096)
    blender_timeout_s: float = Field(600.0, gt=0)
