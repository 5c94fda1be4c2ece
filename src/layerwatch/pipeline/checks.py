"""The checks around the layer comparison: empty bed at job start, first layer, nothing extruded.

:class:`JobChecks` holds what the checks need across a job (the empty-bed
photo and its top views, the camera rays of the working image, the last two
photos' textures) and writes their verdicts into the
:class:`~layerwatch.analysis.result.LayerResult`: ``failed_check``, the
``check_regions`` with their kind, a sentence in ``message``, and a picture
for the operator (:attr:`JobChecks.image`). The pause policy acts on a failed
check at once (:class:`~layerwatch.pipeline.policy.PausePolicy`, rule 5).

* **empty bed** (:meth:`JobChecks.check_bed`, ``[bed_check]``): the frame
  taken when the job starts, before layer 1, against the empty-bed photo
  (:func:`~layerwatch.analysis.bed_check.check_empty_bed`); a result for
  layer -1;
* **first layer** (``[first_layer]``): the photo of layer index 0 against its
  footprint and the empty bed (:func:`~layerwatch.analysis.first_layer.inspect_first_layer`);
* **nothing extruded** (``[extrusion]``): from layer index 2 on, the layer's
  top surface against the photo two layers back (median block NCC,
  :func:`~layerwatch.analysis.extrusion.block_ncc`): flagged when the last two
  layers added no material, so a run-out is caught on the second layer after
  its onset (the first layer's own "nothing extruded" is the first-layer
  inspection's). A layer whose surface is too small to judge alone (fewer than
  :data:`POOL_BELOW_BLOCKS` textured blocks, or less than ``min_area_mm2``: a
  ring of perimeters, thin walls) is judged together with the layer before it:
  both surfaces (not eroded: the beads' edges change with the beads) were
  printed since that photo, so both must have changed. A faint surface whose
  similarity stays under ``min_similarity`` (sensor noise, blur change) is
  flagged from ``still_similarity`` on when it did not rise: at least
  ``still_share`` of its blocks fit that photo better in place than moved by
  the parallax of the two layers' height, and of one layer's
  (:func:`~layerwatch.analysis.extrusion.still_share`; a new layer laid on
  its twin fits the moved photo, and a camera one layer late shows one
  layer's rise on the frame it slips on: a camera fault, never a pause). The texture is computed on the crop of the
  photo that the print can cover only
  (:func:`~layerwatch.analysis.extrusion.box_texture`).

The bed check and the first-layer inspection run only where a bed photo
exists; each is switched by its section's ``enabled``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import cv2
import numpy as np

from layerwatch.analysis.bed_check import check_empty_bed, regions_image
from layerwatch.analysis.extrusion import (
    MIN_PARALLAX_PX,
    block_ncc,
    box_texture,
    rise_parallax_px,
    still_share,
)
from layerwatch.analysis.first_layer import inspect_first_layer
from layerwatch.analysis.result import LayerResult, Region
from layerwatch.analysis.scene_change import (
    image_rays,
    plane_coords,
    plane_maps,
    rays_over,
    working_size,
)
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.geometry.warp import TopViewWarper
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.job_geometry import JobGeometry, geometry_key

__all__ = ["EMPTY_BED", "FIRST_LAYER", "NOTHING_EXTRUDED", "JobChecks", "print_reach_mm", "print_top_z_mm"]

EMPTY_BED, FIRST_LAYER, NOTHING_EXTRUDED = "empty_bed", "first_layer", "nothing_extruded"

#: fewest textured blocks of the surface judged by the nothing-extruded check
MIN_BLOCKS = 3
#: a layer whose own top surface has fewer textured blocks than this, or less area than ``min_area_mm2``, is
#: thin evidence (a 12 mm cube's sparse layers: a 0.7 mm ring of perimeters; a box's sparse infill lines, which
#: the erosion by ``margin_mm`` removes): it is judged together with the layer before it
POOL_BELOW_BLOCKS = 10
#: share of a block the pooled surfaces must cover for the block to be scored (a single layer's: 0.5; a thin
#: ring covers few blocks by half)
POOLED_MIN_SHARE = 0.25
#: pooled surfaces are eroded by at most this, mm: none (a bead's edges change with the bead; eroded by 0.3 mm,
#: sparse infill lines vanish and two layers of thin walls looked alike up to 0.88 in clean prints, not eroded
#: up to 0.80)
POOLED_EROSION_MM = 0.0
#: ``footprint(j) -> (top-view bool mask of layer j, z bottom, z top)`` (the pipeline's references)
FootprintFn = Callable[[int], "tuple[np.ndarray, float, float]"]


def _append(res: LayerResult, text: str) -> None:
    res.message = f"{res.message}; {text}" if res.message else text


#: working px between the pixels whose rays find where the print's prism lies in the image (:meth:`JobChecks._box_maps`)
BOX_SAMPLE_PX = 8


class JobChecks:
    """The per-job state of the checks (module notes).

    Parameters
    ----------
    camera : CameraModel
        Posed camera.
    topview : TopView
    warper : TopViewWarper
        The pipeline's warper (same homographies and lens model).
    config : JobConfig
    bed_photo : ndarray, optional
        Empty-bed photo of the same camera and pose.
    reach_mm : (float, float, float, float), optional
        ``(xmin, ymin, xmax, ymax)`` bed mm that the print's extrusion covers, with
    top_z_mm : float, optional
        its highest layer, mm: the nothing-extruded check then keeps its plane maps and
        textures only on the working-image box whose rays can meet that prism (a
        block-aligned crop: the same blocks and the same result as the whole image, a
        fraction of the memory). Without them the whole image is kept.
    geometry : JobGeometry, optional
        The printer's job geometry (:mod:`layerwatch.pipeline.job_geometry`): the box and plane maps
        are taken from it when an earlier job with the same camera, settings and reach made them.
    """

    def __init__(self, camera: CameraModel, topview: TopView, warper: TopViewWarper, config: JobConfig,
                 bed_photo: np.ndarray | None = None, *,
                 reach_mm: tuple[float, float, float, float] | None = None, top_z_mm: float | None = None,
                 geometry: JobGeometry | None = None) -> None:
        self.camera, self.topview, self.warper, self.config = camera, topview, warper, config
        self.geometry = geometry
        #: the image the nothing-extruded check compares textures on (``[extrusion] working_px``)
        self.size = working_size(camera.image_size, config.extrusion.working_px)
        self._reach = (reach_mm, top_z_mm)
        self._maps: tuple[np.ndarray | None, np.ndarray] | None = None
        self._frame_maps: tuple[np.ndarray, np.ndarray] | None = None  # :meth:`frame`'s rebuilt ``A``, ``B``
        self._frame_planes: dict[float, tuple[np.ndarray, np.ndarray]] | None = None  # :meth:`planes` in a frame
        self._in_frame = False
        #: rows and columns of the working image the check keeps (:meth:`_crop_box`)
        self.box: tuple[slice, slice] = (slice(0, self.size[1]), slice(0, self.size[0]))
        #: RGB picture of the last failed check (``None`` when none failed)
        self.image: np.ndarray | None = None
        #: the last layer's surface similarity and blocks judged by the nothing-extruded check (nan, 0: not judged)
        self.similarity: tuple[float, int] = (float("nan"), 0)
        #: whether that layer was judged together with the layer before it (thin evidence, :data:`POOL_BELOW_BLOCKS`)
        self.pooled = False
        #: that layer's share of blocks that fit the photo two layers back better in place than moved by the two
        #: layers' parallax (nan: not measured; :func:`~layerwatch.analysis.extrusion.still_share`)
        self.still = float("nan")
        self.new_print(bed_photo)

    def new_print(self, bed_photo: np.ndarray | None = None) -> None:
        """Start a job: forget the earlier photos; ``bed_photo`` is the empty bed (``None``: none)."""
        self.bed_photo = None if bed_photo is None else np.asarray(bed_photo)
        self._textures: list[tuple[int, np.ndarray]] = []
        #: the last layer's index, top (mm) and footprint (bits, :func:`numpy.packbits`), to pool thin evidence with
        self._last_footprint: tuple[int, float, np.ndarray] | None = None
        self.image = None

    @property
    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """The rays of :attr:`box` on the layer planes (:func:`~layerwatch.analysis.scene_change.plane_maps`).

        Only ``B`` is kept: for a ray that goes down, ``A = c - C_z B`` with ``c`` the top-view
        position under the camera (``A`` rebuilt per call, a per-layer temporary; it agrees with
        the stored one to ~1e-4 px). A box with a ray that does not go down keeps ``A`` too.
        """
        if self._maps is None:
            if self.geometry is None:
                self.box, self._maps = self._kept_maps()
            else:
                reach, top = self._reach
                key = geometry_key("checks", self.camera, self.topview, size=list(self.size),
                                   block_px=int(self.config.extrusion.block_px),
                                   reach_mm=None if reach is None else [float(v) for v in reach],
                                   top_z_mm=None if top is None else float(top))
                self.box, self._maps = self.geometry.get(key, self._kept_maps)
        stored, b = self._maps
        if stored is not None:
            return stored, b
        if self._frame_maps is not None:
            return self._frame_maps
        C = np.asarray(self.camera.center_mm, np.float64)
        T = self.topview.top_from_bed
        c = np.array([T[0, 0] * C[0] + T[0, 2], T[1, 1] * C[1] + T[1, 2]]).reshape(2, 1, 1)
        out = (c - C[2] * b.astype(np.float64)).astype(np.float32), b
        if self._in_frame:  # the nothing-extruded check and the layer-change channel read it in the same frame
            self._frame_maps = out
        return out

    def _kept_maps(self) -> tuple[tuple[slice, slice], tuple[np.ndarray | None, np.ndarray]]:
        """:meth:`_box_maps` as :attr:`maps` keeps them: the box, and ``A`` only where a ray does not go down."""
        box, (a, b) = self._box_maps()
        return box, (a if bool((a <= -1e5).any()) else None, b)

    @contextmanager
    def frame(self) -> Iterator[None]:
        """Within it, :attr:`maps` builds ``A`` once and :meth:`planes` keeps each plane's top-view coordinates (the
        checks and the layer-change channel of one photo share them, ~1 ms and ~0.2 ms); both are dropped at the end
        (a printer holds nothing more between layers)."""
        self._in_frame = True
        try:
            yield
        finally:
            self._in_frame, self._frame_maps, self._frame_planes = False, None, None

    def planes(self) -> dict[float, tuple[np.ndarray, np.ndarray]]:
        """:func:`~layerwatch.analysis.scene_change.top_coords` of :attr:`maps` by plane height, for
        :func:`~layerwatch.analysis.scene_change.predicted_change`'s ``coords``: within :meth:`frame` one dict for
        the photo (a plane's coordinates computed once, the same arrays for every reader), else a new one."""
        if not self._in_frame:
            return {}
        if self._frame_planes is None:
            self._frame_planes = {}
        return self._frame_planes

    def _box_maps(self) -> tuple[tuple[slice, slice], tuple[np.ndarray, np.ndarray]]:
        """:meth:`_crop_box` and the plane maps ``A``, ``B`` on it, without the rays of the whole working image.

        Each pixel's ray is its own (:func:`_rays`: the values of :func:`image_rays`, bit for bit), and so are
        ``A``, ``B`` and the test of :meth:`_crop_box`. The rays of every :data:`BOX_SAMPLE_PX`-th pixel find
        where the prism's pixels lie; the rays of that region (grown by a sample step and two blocks) give the
        exact box, which is used when none of the region's edge pixels meet the prism (the prism's image is one
        connected patch: it lies inside) and the box lies in the region. Anything else (no sample meets it, an
        edge pixel does) takes the whole image, as before. ~25 ms instead of ~100 at a job's start with the
        example camera (the undistortion of every working pixel was most of a job start).
        """
        h, w = self.size[1], self.size[0]
        prism = self._prism_px()
        if prism is not None:
            rect, z1 = prism
            s, grow = BOX_SAMPLE_PX, BOX_SAMPLE_PX + 2 * int(self.config.extrusion.block_px)
            rows, cols = np.arange(0, h, s), np.arange(0, w, s)
            keep = rays_over(self._plane_maps(rows, cols), rect, 0.0, z1)
            rr, cc = np.flatnonzero(keep.any(axis=1)), np.flatnonzero(keep.any(axis=0))
            if rr.size:
                r0, r1 = max(int(rows[rr[0]]) - grow, 0), min(int(rows[rr[-1]]) + grow + 1, h)
                c0, c1 = max(int(cols[cc[0]]) - grow, 0), min(int(cols[cc[-1]]) + grow + 1, w)
                A, B = self._plane_maps(np.arange(r0, r1), np.arange(c0, c1))
                keep = rays_over((A, B), rect, 0.0, z1)
                edges = ((keep[0].any() and r0 > 0) or (keep[-1].any() and r1 < h)
                         or (keep[:, 0].any() and c0 > 0) or (keep[:, -1].any() and c1 < w))
                box = self._aligned_box(keep, (r0, c0))
                (b0, b1), (d0, d1) = ((box[0].start, box[0].stop), (box[1].start, box[1].stop))
                if keep.any() and not edges and r0 <= b0 and b1 <= r1 and c0 <= d0 and d1 <= c1:
                    crop = (slice(None), slice(b0 - r0, b1 - r0), slice(d0 - c0, d1 - c0))
                    return box, (np.ascontiguousarray(A[crop]), np.ascontiguousarray(B[crop]))
        A, B = plane_maps(image_rays(self.camera, self.size), self.camera.center_mm, self.topview)
        box = self._crop_box(A, B)
        rows_, cols_ = box
        return box, (np.ascontiguousarray(A[:, rows_, cols_]), np.ascontiguousarray(B[:, rows_, cols_]))

    def _plane_maps(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`plane_maps` of the working-image pixels ``rows`` x ``cols`` (each pixel's own values)."""
        return plane_maps(image_rays(self.camera, self.size, rows, cols), self.camera.center_mm, self.topview)

    def _prism_px(self) -> tuple[tuple[float, float, float, float], float] | None:
        """The print's reach (plus 2 mm) as a top-view rectangle ``(u0, v0, u1, v1)`` px and its top (plus 2 mm),
        or None when the job gave no finite reach or top."""
        reach, top = self._reach
        if reach is None or top is None or not np.all(np.isfinite([*reach, top])):
            return None
        pad = 2.0
        (u0, v0), (u1, v1) = self.topview.to_px(np.array([[reach[0] - pad, reach[1] - pad],
                                                          [reach[2] + pad, reach[3] + pad]], float))
        return (u0, v0, u1, v1), top + pad

    def _crop_box(self, A: np.ndarray, B: np.ndarray) -> tuple[slice, slice]:
        """The block-aligned box of working-image pixels whose ray meets the print's prism.

        A pixel's ray meets the plane ``Z = z`` at ``A + z B`` (top-view px); it is kept when
        that segment for ``z`` in [0, top] crosses the reach (plus 2 mm). Outside the box no
        surface pixel can lie, so :func:`block_ncc` on the crop scores the same blocks.
        """
        h, w = self.size[1], self.size[0]
        prism = self._prism_px()
        if prism is None:
            return (slice(0, h), slice(0, w))
        return self._aligned_box(rays_over((A, B), prism[0], 0.0, prism[1]), (0, 0))

    def _aligned_box(self, keep: np.ndarray, at: tuple[int, int]) -> tuple[slice, slice]:
        """The block-aligned box (working-image rows, columns) around the pixels ``keep`` of the region from ``at``."""
        h, w = self.size[1], self.size[0]
        rows, cols = np.flatnonzero(keep.any(axis=1)) + at[0], np.flatnonzero(keep.any(axis=0)) + at[1]
        if rows.size == 0:
            return (slice(0, 0), slice(0, 0))
        bp = int(self.config.extrusion.block_px)
        r0, c0 = max(rows[0] - bp, 0) // bp * bp, max(cols[0] - bp, 0) // bp * bp  # block-aligned starts
        r1, c1 = min(-(-(rows[-1] + 1 + bp) // bp) * bp, h), min(-(-(cols[-1] + 1 + bp) // bp) * bp, w)
        return (slice(int(r0), int(r1)), slice(int(c0), int(c1)))

    def texture_of(self, index: int) -> np.ndarray | None:
        """The nothing-extruded check's texture of the photo of layer ``index`` (``box`` of the working image).

        ``None`` when the check made none for that layer (off, or the photo was not analysed);
        the "changed as predicted" channel then makes its own (:mod:`layerwatch.pipeline.layer_change`).
        """
        return next((t for i, t in self._textures if i == index), None)

    # ------------------------------------------------------------ job start
    def check_bed(self, photo: np.ndarray) -> LayerResult | None:
        """The empty-bed check of the frame taken at job start: a result for layer -1, or ``None`` when off.

        ``status`` ``"ok"`` with ``failed_check = "empty_bed"`` when something lies on the bed,
        ``"error"`` when the frame does not show the bed photo's scene (an alert, never a hold).
        """
        st = self.config.bed_check
        if not st.enabled or self.bed_photo is None:
            return None
        res = LayerResult(layer=-1, z=0.0, metric=self.config.analysis.metric,
                          threshold=float(self.config.analysis.threshold))
        try:
            top, valid = self.warper.warp(photo, 0.0)
            bed_top, bed_valid = self.warper.warp(self.bed_photo, 0.0)
        except (ValueError, TypeError) as exc:
            res.status, res.message = "error", f"bed not checked: {exc}"
            return res
        check = check_empty_bed(top, bed_top, self.topview, st, valid & bed_valid & ~self._marker_discs())
        res.message = check.message
        if check.status == "unchecked":
            res.status = "error"
        elif check.occupied:
            res.failed_check, res.check_regions = EMPTY_BED, check.regions
            self.image = regions_image(top, check.regions, self.topview, "bed not empty", check.changed)
        return res

    # ------------------------------------------------------------ per layer
    def after_layer(self, res: LayerResult, photo: np.ndarray, index: int, footprint: FootprintFn) -> None:
        """Run the layer's checks on an analysed photo and write their verdicts into ``res``."""
        if res.status != "ok":
            return
        if index == 0 and self.config.first_layer.enabled and self.bed_photo is not None:
            self._first_layer(res, photo, footprint)
        if self.config.extrusion.enabled:
            self._extrusion(res, photo, index, footprint)

    def _first_layer(self, res: LayerResult, photo: np.ndarray, footprint: FootprintFn) -> None:
        assert self.bed_photo is not None  # after_layer checks it
        fp, _, z = footprint(0)
        top, valid = self.warper.warp(photo, z)
        bed_top, bed_valid = self.warper.warp(self.bed_photo, z)
        check = inspect_first_layer(top, bed_top, fp, self.topview, self.config.first_layer,
                                    valid=valid & bed_valid)
        if check.ok is False:
            res.failed_check = FIRST_LAYER
            res.check_regions = check.regions
            _append(res, check.message)
            self.image = regions_image(top, check.regions, self.topview, "first layer", check.missing)

    def _extrusion(self, res: LayerResult, photo: np.ndarray, index: int, footprint: FootprintFn) -> None:
        st = self.config.extrusion
        self.similarity, self.pooled, self.still = (float("nan"), 0), False, float("nan")
        maps = self.maps  # sets self.box
        texture = np.ascontiguousarray(box_texture(photo, self.size, self.box))
        earlier = [t for i, t in reversed(self._textures) if i < index][:2]
        self._textures = [(i, t) for i, t in self._textures if i < index][-1:] + [(index, texture)]
        before, self._last_footprint = self._last_footprint, None
        if not earlier:
            return
        fp, _, z = footprint(index)
        self._last_footprint = (index, z, np.packbits(fp))
        if len(earlier) < 2 or index < 2:
            return
        area, surface = self._layer_surface(fp, z, maps, st.margin_mm)
        # earlier[1]: the photo before the last two layers were printed
        share = 0.5
        ncc, scored = block_ncc(texture, earlier[1], surface, st.block_px, min_share=share)
        blocks, judged = int(scored.sum()), f"layer {index}'s top surface ({area:.0f} mm^2"
        if blocks < POOL_BELOW_BLOCKS or area < st.min_area_mm2:  # thin evidence: pool it with the layer before
            if before is None or before[0] != index - 1:
                return
            margin = min(st.margin_mm, POOLED_EROSION_MM)
            if margin != st.margin_mm:
                area, surface = self._layer_surface(fp, z, maps, margin)
            prev = np.unpackbits(before[2], count=fp.size).reshape(fp.shape).astype(bool)
            area_before, surface_before = self._layer_surface(prev, before[1], maps, margin)
            area, surface = area + area_before, surface | surface_before
            share = POOLED_MIN_SHARE
            ncc, scored = block_ncc(texture, earlier[1], surface, st.block_px, min_share=share)
            blocks, judged = int(scored.sum()), f"the top surfaces of layers {index - 1} and {index} ({area:.0f} mm^2"
            self.pooled = True
        if blocks < MIN_BLOCKS or area < st.min_area_mm2:  # not judged
            return
        sim = float(np.median(ncc[scored]))
        self.similarity = (sim, blocks)
        why = f"texture similarity {sim:.2f} >= {st.min_similarity:.2f}"
        t = st.min_similarity
        confidence = float(np.clip((sim - t) / max(1.0 - t, 1e-6), 0, 1))
        if sim < st.still_similarity:
            return
        faint = sim < st.min_similarity
        # flagged when the surface did not rise: its texture fits the earlier photo in place better than moved
        # by the parallax of the layers' height. Under sure_similarity only so: a twin layer (the same infill
        # direction two layers up) can look as alike as a surface nothing was added to, and where the camera
        # sees too little parallax to tell, nothing tells them apart (ExtrusionSettings.sure_similarity)
        if sim < st.sure_similarity:
            d = self._parallax(fp, z, index, footprint, 2)
            if d is None:  # too little parallax to tell
                return
            self.still = still_share(texture, earlier[1], surface, st.block_px, d, scored, share, in_place=ncc)
            if not self.still >= st.still_share:
                return
            # not even one layer's rise: a camera one layer late shows exactly one (the frame it slips on
            # repeats the previous picture, which is one layer above the photo two layers back)
            one = self._parallax(fp, z, index, footprint, 1)
            if one is None:
                if faint:
                    return
            elif not still_share(texture, earlier[1], surface, st.block_px, one, scored, share,
                                 in_place=ncc) >= st.still_share:
                return
            if faint:
                why = (f"texture similarity {sim:.2f} >= {st.still_similarity:.2f}, and {self.still:.0%} of the "
                       f"blocks fit it in place better than raised by one or two layers' height")
                confidence = float(np.clip((self.still - st.still_share) / max(1.0 - st.still_share, 1e-6), 0, 1))
            else:
                why += f", and {self.still:.0%} of the blocks fit it in place better than raised by the layers' height"
        res.failed_check = NOTHING_EXTRUDED
        region = self._footprint_region(fp, area, sim, confidence)
        res.check_regions = [*res.check_regions, region]
        _append(res, f"nothing extruded: {judged}, {blocks} blocks) looks like the photo two layers back "
                     f"({why}); clog or filament run-out?")

    def _parallax(self, fp: np.ndarray, z: float, index: int, footprint: FootprintFn,
                  layers: int) -> np.ndarray | None:
        """Image displacement (working px) of layer ``index``'s surface raised from layer ``index - layers``'s top to ``z``.

        ``None`` when the layers do not rise or the camera sees too little parallax (:data:`MIN_PARALLAX_PX`).
        """
        dz = z - float(footprint(index - layers)[2])
        vv, uu = np.nonzero(fp)
        if dz <= 0 or vv.size == 0:
            return None
        x, y = self.topview.to_mm(np.array([uu.mean(), vv.mean()], float))
        d = rise_parallax_px(self.camera, (float(x), float(y)), z, dz, self.size[0] / self.camera.image_size[0])
        return d if float(np.hypot(*d)) >= MIN_PARALLAX_PX else None

    def _layer_surface(self, fp: np.ndarray, z: float, maps: tuple[np.ndarray, np.ndarray],
                       margin_mm: float) -> tuple[float, np.ndarray]:
        """A layer's footprint ``fp`` eroded by ``margin_mm``: its area (mm^2) and its top surface in :attr:`box`.

        The top surface: the eroded footprint on the layer's plane ``z`` seen through the camera
        (:func:`~layerwatch.analysis.scene_change.predicted_change` of one plane), where the
        top view covers it.
        """
        k = int(round(2 * margin_mm * self.topview.px_per_mm)) | 1
        inner: np.ndarray = np.asarray(fp, np.uint8)
        if k > 1:
            inner = cv2.erode(inner, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
        area = float(np.count_nonzero(inner)) / self.topview.px_per_mm ** 2
        mx, my = plane_coords(maps, z, self.planes())
        H, W = self.topview.shape
        surface = cv2.remap(inner, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0
        return area, surface & (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)

    def _marker_discs(self) -> np.ndarray:
        """Top-view pixels of the bed markers and 3 mm around them: white dots clip differently under new light."""
        out = np.zeros(self.topview.shape, np.uint8)
        pts = self.camera.markers_mm if self.camera.markers_mm is not None else self.config.markers.positions_mm
        if pts is None:
            return out.astype(bool)
        r = int(round((self.config.markers.diameter_mm / 2 + 3.0) * self.topview.px_per_mm))
        for u, v in np.round(self.topview.to_px(np.asarray(pts, float).reshape(-1, 2))).astype(int):
            cv2.circle(out, (int(u), int(v)), r, 1, -1)
        return out.astype(bool)

    def _footprint_region(self, fp: np.ndarray, area: float, sim: float, confidence: float) -> Region:
        vv, uu = np.nonzero(fp)
        (x0, y0), (x1, y1) = self.topview.to_mm(np.array([[uu.min(), vv.max()], [uu.max(), vv.min()]], float))
        cx, cy = self.topview.to_mm(np.array([uu.mean(), vv.mean()]))
        return Region(area_mm2=area, bbox_mm=(float(x0), float(y0), float(x1), float(y1)),
                      centroid_mm=(float(cx), float(cy)), n_blocks=int(np.ceil(area / 4.0)),
                      mean_similarity=float(sim), min_similarity=float(sim), kind=NOTHING_EXTRUDED,
                      kind_confidence=round(confidence, 3))


def print_reach_mm(toolpath: Toolpath) -> tuple[float, float, float, float] | None:
    """``(xmin, ymin, xmax, ymax)`` of every segment of ``toolpath`` (skirt, brim, tower included), mm."""
    if toolpath.n_segments == 0:
        return None
    xy = np.concatenate([toolpath.start[:, :2], toolpath.end[:, :2]])
    lo, hi = np.nanmin(xy, axis=0), np.nanmax(xy, axis=0)
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def print_top_z_mm(toolpath: Toolpath) -> float | None:
    """The highest layer of ``toolpath``, mm."""
    return float(np.nanmax(toolpath.z)) if toolpath.n_segments else None
