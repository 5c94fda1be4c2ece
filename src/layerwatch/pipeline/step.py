"""One layer in, one :class:`~layerwatch.analysis.result.LayerResult` out.

:class:`LayerPipeline` chains the stages of the method for a job whose
G-code (toolpath), camera pose and config are known:

1. **warp** the photo into the top view of the layer's plane ``Z = z``
   (:class:`~layerwatch.geometry.warp.TopViewWarper`, eq. 3);
2. **reference**: render the ideal layer (:class:`~layerwatch.render.fast.StackRenderer`,
   incremental, memoised in memory and optionally on disk) as the camera sees
   it through the layer's plane (``render.view = "camera"``, the default:
   walls and the parallax of lower layers as in the warped photo, see
   :mod:`layerwatch.render.camera_view`; with ``render.reference = "volume"``
   the rays run through the layers' occupancy, so windows, bridges and
   overhangs show what lies behind and under them, see
   :mod:`layerwatch.render.volume`), and optionally
   blur it by the camera's sampling footprint on that plane
   (:func:`~layerwatch.render.camera_match.match_camera`);
3. **analyse**: HOG of both images, similarity heatmap, anomaly ratio a%
   (eq. 5) and regions (:func:`~layerwatch.analysis.scoring.analyze_layer`);
4. **scene** (``[scene] enabled``, on in the recommended settings): the
   camera image outside the layers' predicted change is compared with the
   scene's expected appearance (:class:`~layerwatch.pipeline.scene.SceneModel`,
   seeded by the empty-bed photo when given); what changed there is
   ``outside_anomalous_mm2`` and ``outside_regions`` (bed mm) of the result,
   beside a% (which stays eq. 5 over the printed area). A frame that does not
   show the scene at all is rejected like a frame-gate rejection;
5. **type** every failing region (``regions`` and ``outside_regions``):
   its kind, confidence and, for a moved part, the displacement in mm
   (:class:`~layerwatch.analysis.failure_typing.FailureTyper`; only on
   layers with a region, ``timings_ms["typing"]``).
6. **checks** (:class:`~layerwatch.pipeline.checks.JobChecks`): the first
   layer against its footprint and the empty bed, and nothing extruded on
   the last two layers; a failure sets ``failed_check`` and
   ``check_regions``. The empty-bed check of the frame taken at job start is
   :meth:`LayerPipeline.check_bed`;
7. **changed as predicted** (series mode; after the checks, whose texture
   it reuses; ``[layer_change] enabled``, on in the recommended settings;
   :class:`~layerwatch.pipeline.layer_change.LayerChange`): blocks of the
   new layer's footprint that look as in the previous photo of the print,
   and did in the pair before (a gap in a thin wall, a patch missing from
   the infill), become failing regions typed ``thin_wall``/``infill_defect`` and count
   into a% (eq. 5 over the printed area); ``result.layer_change`` says what
   was judged.

This is the one per-layer step: the monitor, ``analyze``, the demo and the
evaluation harness (which sweeps other measures and thresholds over the
same step's HOG blocks) all call :meth:`LayerPipeline.process`; the pause
decision after it is :class:`~layerwatch.pipeline.policy.PausePolicy`'s.

Frame-quality gate (hook). Between the photo's arrival and the warp,
:meth:`LayerPipeline.process` calls ``frame_gate(photo, previous, settings)``
when one is given (``previous``: the last photo that passed, ``settings``:
``config.analysis``). It returns ``None`` for a usable frame or a one-line
reason; a rejected frame gives ``status="error"`` with ``"frame rejected:
<reason>"`` (the policy alerts on it and never pauses) and does not become
``previous``. ``layerwatch.analysis.frame_quality.assess_frame`` is meant to
be wired here (an adapter turning its verdict into ``None``/reason).

The pipeline never raises for a bad photo or a failed warp: the result has
``status="error"`` and a one-line ``message``; a caller (monitor, CLI,
evaluation) logs it and goes on with the next layer. Configuration mistakes
made before any photo arrives (no pose, layer out of range) do raise.

References
----------
Petsiuk & Pearce (2022), Sections 2.3-2.4, eqs. (1)-(5).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator
from functools import partial
from pathlib import Path

import numpy as np

from layerwatch.analysis.failure_typing import FailureTyper
from layerwatch.analysis.ledges import ledge_regions, slab_layers, slab_tops
from layerwatch.analysis.part_colour import off_colour, off_colour_blocks, rim_material
from layerwatch.analysis.region_outline import region_box
from layerwatch.analysis.result import LayerResult
from layerwatch.analysis.scene_change import change_regions, working_to_top
from layerwatch.analysis.scoring import analyze_layer, grey_u8, near_footprint, reference_hog
from layerwatch.analysis.settings import AnalysisSettings
from layerwatch.analysis.view_shift import (
    ViewShift,
    marker_offset_top_px,
    measure_view_shift,
    moved_back,
)
from layerwatch.errors import LayerwatchError, RenderError
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.warp import TopViewWarper, check_image
from layerwatch.pipeline.checks import JobChecks, print_reach_mm, print_top_z_mm
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.job_geometry import JobGeometry
from layerwatch.pipeline.layer_change import LayerChange
from layerwatch.pipeline.policy import Decision, PausePolicy, layer_alarm
from layerwatch.pipeline.previous_view import PreviousView, typing_area
from layerwatch.pipeline.scene import SceneModel, SceneObservation
from layerwatch.pipeline.scene_hold import failing_blocks
from layerwatch.pipeline.shared_references import SharedReferences, reference_identity
from layerwatch.render.cache import ReferenceCache, toolpath_hash
from layerwatch.render.camera_match import match_camera as camera_matched
from layerwatch.render.fast import StackRenderer
from layerwatch.render.mask import gcode_mask

__all__ = ["FrameGate", "LayerPipeline", "Reference", "judge_layers"]

#: ``gate(photo, previous_photo_or_None, settings) -> None | reason``: the frame-quality hook (module notes)
FrameGate = Callable[[np.ndarray, "np.ndarray | None", AnalysisSettings], "str | None"]


class Reference:
    """A reference of one layer as the pipeline uses it.

    Attributes
    ----------
    image : ndarray, shape (H, W), uint8
        Grey reference (camera-matched when the pipeline does that).
    footprint : ndarray, shape (H, W), bool
        Pixels printed in this layer.
    z : float
        Layer top, mm.
    hog : (ndarray, ndarray) or None
        The image's HOG cell histograms and block energies
        (:func:`~layerwatch.analysis.scoring.reference_hog` with the
        pipeline's analysis settings), computed with the reference so that a
        prepared layer costs only the photo's HOG.
    registration : ndarray, shape (H, W), uint8, or None
        The same view with ``[render] registration_darkening`` as its depth darkening, which the
        view shift and the part registration read (:attr:`registered`); ``None``: they read ``image``.
    """

    __slots__ = ("image", "footprint", "z", "hog", "registration")

    def __init__(self, image: np.ndarray, footprint: np.ndarray, z: float,
                 hog: tuple[np.ndarray, np.ndarray] | None = None, registration: np.ndarray | None = None) -> None:
        self.image, self.footprint, self.z, self.hog = image, footprint, float(z), hog
        self.registration = registration

    @property
    def registered(self) -> np.ndarray:
        """The grey reference the registrations read: :attr:`registration`, else :attr:`image`."""
        return self.image if self.registration is None else self.registration


class LayerPipeline:
    """Analyse camera photos of a print layer by layer: the job context and the per-layer step.

    It holds what a job fixes (the toolpath, the posed camera, the observed
    square of the bed as a :class:`~layerwatch.geometry.topview.TopView`, the
    resolved :class:`~layerwatch.pipeline.config.JobConfig`) and the state
    that outlives one photo (the reference renderer and its memo/cache, the
    last top view, the frame gate's previous photo).

    Parameters
    ----------
    toolpath : Toolpath
        The job's parsed G-code.
    camera : CameraModel
        Calibrated camera with a bed pose (``rvec``/``tvec``).
    config : JobConfig, optional
        Top view, render and analysis settings (defaults when omitted);
        ``[topview] scale = "camera"`` is resolved for ``camera``
        (:meth:`JobConfig.for_camera`; :attr:`config` holds the result).
    cache_dir : str or Path, optional
        Folder of an on-disk reference cache (:class:`~layerwatch.render.cache.ReferenceCache`);
        identical parts then render each layer once across runs.
    match_camera : bool
        Blur references by the camera's footprint on the layer plane (see
        :mod:`layerwatch.render.camera_match`). Off by default: on simulated
        photos it did not raise the share of clean blocks above cosine 0.7
        (75.5 % vs 75.7 %) and lowered detection (``docs/evaluation/README.md``).
    all_metrics : bool
        Score all twelve measures per layer into ``result.per_metric``.
    memo : int
        References kept in memory (least recently used dropped).
    frame_gate : callable, optional
        Frame-quality check run before the warp (see the module notes).
    bed_photo : ndarray, optional
        Empty-bed photo of the same camera and pose: the scene channel's first
        expected appearance (without it, the first accepted photo is).
    shared : SharedReferences, optional
        References shared with other pipelines of the process (a farm's printers printing the same
        file with the same camera model, :mod:`layerwatch.pipeline.shared_references`): a layer another
        pipeline rendered is read, not rendered; a layer rendered here is stored.
    geometry : JobGeometry, optional
        The printer's job geometry (:mod:`layerwatch.pipeline.job_geometry`): the scene channel's view
        maps and the checks' box maps of an earlier job of the printer with the same camera, settings and
        print reach are taken, not computed again (a farm printer's job start; the same values).

    Raises
    ------
    LayerwatchError
        The camera has no pose or the toolpath has no layers.
    """

    def __init__(
        self,
        toolpath: Toolpath,
        camera: CameraModel,
        config: JobConfig | None = None,
        cache_dir: str | Path | None = None,
        *,
        match_camera: bool = False,
        all_metrics: bool = False,
        memo: int = 8,
        frame_gate: FrameGate | None = None,
        bed_photo: np.ndarray | None = None,
        shared: SharedReferences | None = None,
        geometry: JobGeometry | None = None,
    ) -> None:
        if toolpath.n_layers == 0:
            raise RenderError(f"{toolpath.source} has no layers; check the G-code has extrusion moves.")
        self.toolpath = toolpath
        self.camera = camera
        self.config = (config or JobConfig()).for_camera(camera)  # [topview] scale = "camera" resolved
        self.topview = self.config.topview.topview()
        self.warper = TopViewWarper(camera, self.topview)
        self.renderer = StackRenderer(toolpath, self.topview, self.config.render, self.camera)
        self.match_camera = bool(match_camera)
        self.all_metrics = bool(all_metrics)
        self.frame_gate = frame_gate
        #: last photo the frame gate passed (its ``previous`` argument)
        self.previous_photo: np.ndarray | None = None
        #: the print's last analysed photo as its top view: what the failure typing compares the new photo with
        #: on the new plane (:mod:`layerwatch.pipeline.previous_view`; ~0.3 MB, not the 6 MB photo)
        self._before: PreviousView | None = None
        #: the top-view rows and columns any layer's typing reads of the previous photo
        self._typing_area = typing_area(print_reach_mm(toolpath), self.topview)
        #: grey top view and valid mask of the last successfully warped photo (for overlays)
        self.last_top: np.ndarray | None = None
        self.last_valid: np.ndarray | None = None
        #: the scene channel's model (``None`` when ``[scene] enabled`` is off)
        reach, top_z = print_reach_mm(toolpath), print_top_z_mm(toolpath)
        scene_reach = _grown(reach, 0.5 * float(np.nanmax(toolpath.width)))
        self.scene = (None if not self.config.scene.enabled
                      else SceneModel(camera, self.topview, self.config.scene, bed_photo, reach_mm=scene_reach, top_z_mm=top_z)
                      if geometry is None
                      else geometry.scene(camera, self.topview, self.config.scene, bed_photo, reach_mm=scene_reach,
                                          top_z_mm=top_z))
        #: the residual camera shift undone before the comparison (``[analysis] register_mm``)
        self.view_shift = ViewShift(self.config.analysis.register_mm * self.topview.px_per_mm)
        #: where the markers' offset is turned into the top view's: the print's centre, bed mm
        self._centre_mm = None if reach is None else (0.5 * (reach[0] + reach[2]), 0.5 * (reach[1] + reach[3]))
        #: the bed markers' offset in the photo :meth:`process` analyses next (:meth:`markers_moved`)
        self._markers: tuple[tuple[float, float], tuple[int, int]] | None = None
        #: types the failing regions of each analysed photo (:mod:`layerwatch.analysis.failure_typing`)
        self.typer = FailureTyper(toolpath, self.topview, camera.center_mm if camera.has_pose else None)
        #: the empty-bed, first-layer and nothing-extruded checks
        self.checks = JobChecks(camera, self.topview, self.warper, self.config, bed_photo,
                                reach_mm=reach, top_z_mm=top_z, geometry=geometry)
        #: the "changed as predicted" channel (``None`` when ``[layer_change] enabled`` is off)
        self.layer_change = (LayerChange(self.checks, self.topview, self.warper, toolpath, self.config.layer_change,
                                         lambda: self.config.policy.min_area_mm2)  # live: the policy's current value
                             if self.config.layer_change.enabled else None)
        self._memo: OrderedDict[int, Reference] = OrderedDict()
        self._memo_size = max(1, int(memo))
        #: the references of the layer :meth:`process` analysed last and of the one before it, kept past the
        #: memo (:meth:`reference`): ``(layer, image, footprint bits, z, registration image or None)``
        self._own: tuple[int, np.ndarray, np.ndarray, float, np.ndarray | None] | None = None
        self._kept: tuple[int, np.ndarray, np.ndarray, float, np.ndarray | None] | None = None
        self._cache = None
        self._hash = None
        #: the references shared with the process's other pipelines, and this pipeline's key there (made when first used)
        self.shared = shared
        self._identity: str | None = None
        if cache_dir is not None:
            self._cache = ReferenceCache(cache_dir)
            self._hash = toolpath_hash(toolpath)

    # ------------------------------------------------------------ references
    @property
    def view_center_mm(self) -> np.ndarray | None:
        """Camera centre the references are seen from (``render.view = "camera"``), else ``None``."""
        if self.config.render.view != "camera" or not self.camera.has_pose:
            return None
        return np.asarray(self.camera.center_mm, np.float64)

    def _render(self, index: int):
        c = self.view_center_mm
        if self._cache is None or self._hash is None:
            return self.renderer.render(index, c)
        kind = "ref" if c is None else "cam:" + ",".join(f"{v:.3f}" for v in c)
        key = self._cache.key(self._hash, self.config.render, self.topview, index, kind=kind)
        return self._cache.get_or_render(key, lambda: self.renderer.render(index, c))

    def reference(self, index: int) -> Reference:
        """The (memoised) reference of layer ``index``.

        Besides the memo, the pipeline keeps the image and footprint (as bits, ~0.4 MB at 600 x 600 px) of
        the layer :meth:`process` analysed last and of the one before it (:meth:`forget_references` drops
        the older): the monitor's lag check asks for layer ``k - 1`` right after the photo of layer ``k``,
        and a farm pipeline (one reference memoised, forgotten once the layer is recorded) rendered it
        again, from the first layer, as the renderer only moves up (a lower layer resets its stack): a
        cost that grows with the print's height (~33 ms at layer 20 of the example part). A kept layer
        is the image its render gave, with its HOG computed again (the same function of the same image):
        the same :class:`Reference`, array for array (``tests/render/test_kept_reference.py``). With
        :attr:`shared` references, a layer past the memo is looked up there first and what is made here is
        stored there (read-only: a shared reference's arrays are not writeable).

        Raises
        ------
        RenderError
            ``index`` is not a layer of the toolpath.
        """
        n = self.toolpath.n_layers
        if not 0 <= index < n:
            raise RenderError(f"layer {index} does not exist (0..{n - 1}); check the photo's layer number.")
        hit = self._memo.get(index)
        if hit is not None:
            self._memo.move_to_end(index)
            return hit
        if self.shared is not None and self._identity is None:
            self._identity = reference_identity(self.toolpath, self.camera, self.config, self.topview, self.match_camera)
        shared = self.shared.get(self._identity, index) if self.shared is not None and self._identity else None
        ref = shared if isinstance(shared, Reference) else None
        if ref is None:
            ref = self._new_reference(index)
            if self.shared is not None and self._identity:
                self.shared.put(self._identity, index, ref)
        self._memo[index] = ref
        while len(self._memo) > self._memo_size:
            self._memo.popitem(last=False)
        return ref

    def _new_reference(self, index: int) -> Reference:
        """The reference of layer ``index`` made here: from a kept layer (:meth:`reference`) or rendered."""
        kept = next((k for k in (self._own, self._kept) if k is not None and k[0] == index), None)
        if kept is not None:  # a layer analysed on this or the previous photo, past the memo (docstring)
            _, kept_image, bits, z, kept_reg = kept
            image, registration = kept_image.copy(), None if kept_reg is None else kept_reg.copy()
            footprint = np.unpackbits(bits, count=image.size).view(bool).reshape(image.shape)
        else:
            r = self._render(index)
            z = self.toolpath.layers[index].z
            image, footprint, registration = r.image, r.mask, r.registration
            if self.match_camera:
                image = camera_matched(image, self.camera, self.topview, z)
                if registration is not None:
                    registration = camera_matched(registration, self.camera, self.topview, z)
        return Reference(image, footprint, z, reference_hog(image, self.config.analysis), registration)

    def prepare(self, layers: Iterable[int] | None = None) -> None:
        """Render references ahead of the print (in increasing order, into the memo/cache).

        Only the last ``memo`` layers stay in memory; use ``cache_dir`` to keep all.
        """
        for i in sorted(range(self.toolpath.n_layers) if layers is None else layers):
            self.reference(int(i))

    def replace_toolpath(self, toolpath: Toolpath) -> None:
        """Judge the following layers against ``toolpath`` (the same layers, e.g. without a cancelled object).

        Forgets the memoised references; the on-disk cache keys on the new toolpath.
        """
        if toolpath.n_layers != self.toolpath.n_layers:
            raise RenderError(f"the new toolpath has {toolpath.n_layers} layers, the job {self.toolpath.n_layers}")
        self.toolpath = toolpath
        self.renderer = StackRenderer(toolpath, self.topview, self.config.render, self.camera)
        self._identity = None  # another toolpath: other shared references
        if self.layer_change is not None:
            self.layer_change.toolpath = toolpath
        self._memo.clear()
        self._own = self._kept = None
        if self._cache is not None:
            self._hash = toolpath_hash(toolpath)

    def forget_references(self) -> None:
        """Drop the memoised references (the renderer keeps its layer stack: the next layer stays incremental).

        A farm printer calls it once a layer is recorded: the next photo is of another layer, so
        the reference would only be held (about 1.1 MB at 600 x 600 px), never used. The image and
        footprint bits of the layer analysed last stay (~0.4 MB, :meth:`reference`): the next photo's
        lag check may ask for that layer.
        """
        self._memo.clear()
        self._kept = None

    def _keep(self, index: int, ref: Reference) -> None:
        """Keep the reference of the layer analysed now past the memo; the one analysed before moves down."""
        if self._own is not None and self._own[0] == index:
            return
        self._kept = self._own
        self._own = (index, ref.image.copy(), np.packbits(np.asarray(ref.footprint, bool), axis=None), ref.z,
                     None if ref.registration is None else ref.registration.copy())

    def footprint(self, index: int) -> tuple[np.ndarray, float, float]:
        """Top-view footprint of layer ``index`` (its reference's) and its bottom and top heights, mm."""
        return self.reference(index).footprint, *self._layer_heights(index)

    def plan_footprint(self, index: int) -> tuple[np.ndarray, float, float]:
        """:meth:`footprint` from the plan alone (:func:`~layerwatch.render.mask.gcode_mask`, the beads rasterised
        as the renderer does): nothing rendered, wherever the renderer's stack stands."""
        return gcode_mask(self.toolpath, index, self.topview), *self._layer_heights(index)

    def _layer_heights(self, index: int) -> tuple[float, float]:
        lay = self.toolpath.layers[index]
        return float(lay.z - (lay.height if lay.height > 0 else 0.2)), float(lay.z)

    def new_print(self, bed_photo: np.ndarray | None = None) -> None:
        """Forget the scene of the previous print (the scene channel starts again from ``bed_photo``)."""
        self.previous_photo = None
        self._before = None
        self.typer.reset()
        self.view_shift.reset()
        if self.scene is not None:
            self.scene.reset(bed_photo)
        self.checks.new_print(bed_photo)
        if self.layer_change is not None:
            self.layer_change.new_print()

    def check_bed(self, photo: np.ndarray) -> LayerResult | None:
        """The empty-bed check of the frame taken when the job starts (layer -1; see :class:`JobChecks`).

        ``None`` when the check is off or there is no bed photo. A bed that is not empty gives
        ``failed_check = "empty_bed"`` (the policy holds the job); :attr:`JobChecks.image` shows it.
        """
        try:
            return self.checks.check_bed(photo)
        except LayerwatchError as exc:
            return LayerResult(layer=-1, z=0.0, status="error", message=f"bed not checked: {exc}")

    def acknowledge(self) -> int:
        """The operator accepted the changes beside the print: the scene channel stops reporting them.

        Call it with :meth:`~layerwatch.pipeline.policy.PausePolicy.acknowledge`
        (resume). Returns the working-image pixels the expected appearance took
        from the last photo (0 when the channel is off or nothing changed).
        """
        return 0 if self.scene is None else self.scene.acknowledge()

    # ------------------------------------------------------------ analysis
    def markers_moved(self, offset_px: tuple[float, float] | None, photo_size: tuple[int, int]) -> None:
        """How far the bed markers lie from their calibrated places in the photo :meth:`process` analyses next.

        The monitor's camera-fault gate finds the markers in each frame
        (:func:`~layerwatch.analysis.frame_quality.marker_offset_px`); a camera that moved moves them, a part that
        moved on the bed does not, so the view shift undone starts from it (:class:`~layerwatch.analysis.view_shift.ViewShift`).

        Parameters
        ----------
        offset_px : (float, float) or None
            Median ``(du, dv)`` of the markers in the photo, px; ``None``: not seen (nothing is assumed).
        photo_size : (int, int)
            ``(w, h)`` of that photo.
        """
        if offset_px is None or len(offset_px) != 2 or not np.all(np.isfinite(offset_px)):
            self._markers = None  # not seen, or not a finite offset: nothing is assumed
            return
        self._markers = ((float(offset_px[0]), float(offset_px[1])), (int(photo_size[0]), int(photo_size[1])))

    def _markers_top_px(self, markers: tuple[tuple[float, float], tuple[int, int]] | None,
                        z: float) -> tuple[float, float] | None:
        """The markers' offset handed for a photo (:meth:`markers_moved`) as the top view's (:func:`marker_offset_top_px`)."""
        if markers is None or self._centre_mm is None:
            return None
        return marker_offset_top_px(self.camera, self.topview, self._centre_mm, z, *markers)

    def top_view(self, photo: np.ndarray, z: float,
                 box: tuple[slice, slice] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The photo warped to the top view of the plane ``Z = z`` as the analysis reads it.

        ``box`` (rows, columns): only that part of the top view (``top[box]``, ``valid[box]``
        pixel for pixel, for the cost of the box; not checked for being seen).

        Returns
        -------
        top : ndarray, shape (H, W), uint8
            Grey top view (:func:`~layerwatch.analysis.scoring.grey_u8`).
        valid : ndarray, shape (H, W), bool
            Pixels the camera saw.

        Raises
        ------
        LayerwatchError
            The photo cannot be warped or shows nothing of the observed area.
        """
        if box is not None:
            part, valid = self.warper.warp(photo, z, box)
            return grey_u8(part), valid
        _, top, valid = self._top_views(photo, z)
        return top, valid

    def keep_top_view(self, photo: np.ndarray, z: float, box: tuple[slice, slice]) -> bool:
        """Keep what :meth:`top_view` of ``box`` on the plane ``z`` needs for a later photo of the same size, when
        this photo's warp onto that plane is still cached (:meth:`TopViewWarper.keep_box
        <layerwatch.geometry.warp.TopViewWarper.keep_box>`: the same pixels, without building the table again).
        """
        h, w = np.asarray(photo).shape[:2]
        return self.warper.keep_box(z, box, (w, h))

    def _top_views(self, photo: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`top_view` with the colour top view first (as warped, for the failure typing's colour evidence)."""
        top, valid = self.warper.warp(photo, z)
        if not valid.any():
            raise LayerwatchError("the photo does not show the observed area; check the camera pose.")
        return top, grey_u8(top), valid

    def process(self, photo: np.ndarray, layer_index: int) -> LayerResult:
        """Analyse the photo taken after layer ``layer_index``: the per-layer step.

        Parameters
        ----------
        photo : ndarray, uint8, shape (h, w) or (h, w, 3)
            Camera frame (BGR as cv2.imread gives, distorted as captured).
        layer_index : int
            0-based layer index in the toolpath.

        Returns
        -------
        LayerResult
            ``status`` ``"ok"``/``"skipped"``, or ``"error"`` with ``message``
            when the photo cannot be used (wrong type/shape, rejected by the
            frame gate, failed warp, nothing visible, out of memory); ``timings_ms`` has
            ``reference``, ``warp``, ``analysis`` (and the analysis' own ``hog``,
            ``metric``, ``regions``), ``scene`` (when on) and ``total``. :attr:`last_top` and
            :attr:`last_valid` hold the top view of an analysed photo.

        Raises
        ------
        Exception
            Anything else raised inside the analysis is a bug in layerwatch, not a property of the photo, and is
            not turned into a layer's error: the CLI exits 70 on it, the monitor records it as a pipeline fault
            and keeps watching (``monitor.service.pipeline_error``).
        """
        t0 = time.perf_counter()
        st = self.config.analysis
        index = int(layer_index) if isinstance(layer_index, (int, np.integer)) else -1
        z = float(self.toolpath.layers[index].z) if 0 <= index < self.toolpath.n_layers else 0.0
        base = {"layer": index, "z": z, "metric": st.metric, "threshold": float(st.threshold)}
        timings: dict[str, float] = {}
        self.last_top = self.last_valid = None
        markers, self._markers = self._markers, None  # handed for this photo only
        try:
            if not isinstance(layer_index, (int, np.integer)) or isinstance(layer_index, bool):
                raise LayerwatchError(f"layer index must be an integer, got {type(layer_index).__name__}.")
            photo = check_image(photo)  # the photo at the edge: an array of a camera frame's type and shape
            if photo.dtype not in (np.uint8, np.uint16):
                raise LayerwatchError(f"photo has dtype {photo.dtype}; pass an 8-bit image (as cv2.imread gives).")
            reason = self._frame_rejected(photo)
            if reason is not None:
                return self._error(base, f"frame rejected: {reason}", timings, t0)
            ref = self.reference(int(layer_index))
            self._keep(index, ref)
            obs = None
            if self.scene is not None:
                obs = self.scene.observe(photo, index, self.footprint, self.plan_footprint)
                timings["scene"] = obs.ms
                if obs.rejected is not None:
                    res = self._error(base, f"frame rejected: {obs.rejected}", timings, t0)
                    res.scene = obs.stats()
                    return res
            t1 = time.perf_counter()
            timings["reference"] = (t1 - t0) * 1e3 - timings.get("scene", 0.0)
            top_bgr, top, valid = self._top_views(photo, ref.z)
            shift = self.view_shift.update(measure_view_shift(top, ref.registered, ref.footprint, valid)
                                           if self.view_shift.max_px > 0 else None, self._markers_top_px(markers, ref.z))
            top, valid, top_bgr = moved_back(shift, top, valid, top_bgr)
            t2 = time.perf_counter()
            timings["warp"] = (t2 - t1) * 1e3
            coloured = None
            if st.off_colour:  # the printed layer's blocks of another material than the part's filament
                t_col = time.perf_counter()
                coloured = off_colour_blocks(top_bgr, ref.footprint, valid, st.cell_px, st.block_cells,
                                             self.topview.px_per_mm)
                timings["colour"] = (time.perf_counter() - t_col) * 1e3
            res = analyze_layer(top, ref.image, ref.footprint, self.topview, st, valid=valid, layer=index,
                                z=ref.z, all_metrics=self.all_metrics, ref_hog=ref.hog, off_colour=coloured)
            res.view_shift_px = shift
            if obs is not None:
                self._scene_result(res, obs, photo, ref.z, valid, top_bgr, ref.footprint)
            t_type = time.perf_counter()
            before = self._before if self._before is not None and self._before.layer < index else None
            self.typer.type_result(res, top_bgr, top, ref.registered, ref.footprint, valid,
                                   previous=None if before is None else partial(before.top, self.warper, ref.z))
            res.timings_ms["typing"] = (time.perf_counter() - t_type) * 1e3
            with self.checks.frame():  # the checks' plane maps built once for both
                self.checks.after_layer(res, photo, index, self.footprint)
                if self.layer_change is not None:  # after the typing (its regions come typed) and the checks' texture
                    self.layer_change.judge(res, photo, index, self.footprint)
        except LayerwatchError as exc:
            return self._error(base, str(exc), timings, t0)
        except MemoryError:
            return self._error(base, "out of memory analysing the photo; lower the camera resolution or close other "
                               "programs.", timings, t0)
        # what the next photo's typing reads of this one (a copy of the print's surroundings, ~0.3 MB)
        self._before = PreviousView.keep(index, ref.z, top, valid, self._typing_area, shift)
        t3 = time.perf_counter()
        res.timings_ms = {**timings, "analysis": (t3 - t2) * 1e3,
                          **{k: v for k, v in res.timings_ms.items() if k != "total"},
                          "total": (t3 - t0) * 1e3}
        self.last_top, self.last_valid = top, valid
        return res

    def _scene_result(self, res: LayerResult, obs: SceneObservation, photo: np.ndarray, z: float,
                      valid: np.ndarray, top_bgr: np.ndarray, footprint: np.ndarray) -> None:
        """The scene channel's outside anomaly into ``res``, then ``E`` takes the layer (analysed photos only)."""
        assert self.scene is not None  # only called when the scene channel produced ``obs``
        t = time.perf_counter()
        h, w = np.asarray(photo).shape[:2]
        self.scene.fill_result(res, obs, self.warper, z, (w, h), valid)
        self._hidden_ledges(res, obs, z, (w, h), valid, top_bgr, footprint)
        if self.config.analysis.off_colour:
            self._rim_objects(res, valid, top_bgr, footprint)
        if res.heatmap is not None and res.grid is not None and layer_alarm(
                float(res.anomaly_ratio), float(res.anomalous_area_mm2 + res.uncounted_mm2), self.config.policy):
            self.scene.hold_failing(obs, failing_blocks(res, self.topview.shape), z)  # "a failure that stays, counts"
        self.scene.update(obs)
        ms = obs.ms + (time.perf_counter() - t) * 1e3
        res.timings_ms["scene"] = ms
        if res.scene is not None:
            res.scene.ms = round(ms, 3)

    def _hidden_ledges(self, res: LayerResult, obs: SceneObservation, z: float, photo_size: tuple[int, int],
                       valid: np.ndarray, top_bgr: np.ndarray, footprint: np.ndarray) -> None:
        """Lower floors no earlier photo showed, and the hidden tops of the layer's slab (another object of a
        plate printed in turns), judged by the reference's HOG and by the part's colour
        (:mod:`layerwatch.analysis.ledges`): their failing regions join the change beside the printed layer."""
        if res.heatmap is None or res.mask is None:
            return
        st = self.config.analysis
        hidden = obs.hidden_ledges
        top = None
        if hidden is not None and hidden.any():
            top = (working_to_top(hidden.view(np.uint8), self.warper, z, photo_size) > 0) & valid
        judged, tops = self._slab_blocks(res, obs, z, photo_size, valid, footprint)
        if top is None and judged is None:
            return
        heat = res.heatmap
        if judged is not None and tops is not None and st.off_colour:  # the slab's tops: the printed layer's colour test
            other = off_colour_blocks(top_bgr, tops, valid, st.cell_px, st.block_cells, self.topview.px_per_mm)
            if other is not None and other.any():
                heat = np.where(other & judged, np.minimum(heat, np.float32(0.5 * st.threshold)), heat)
        coloured = None
        if top is None:
            top = np.zeros(valid.shape, bool)
        else:
            coloured = off_colour(top_bgr, footprint & valid, top, st.cell_px)
        found = ledge_regions(heat, res.mask, top, st.threshold, st.cell_px, st.block_cells, self.topview,
                              self.config.scene.min_region_mm2, coloured, judged)
        if found:
            res.outside_regions = sorted(res.outside_regions + found, key=lambda r: -r.area_mm2)
            res.outside_anomalous_mm2 += float(sum(r.area_mm2 for r in found))

    def _slab_blocks(self, res: LayerResult, obs: SceneObservation, z: float, photo_size: tuple[int, int],
                     valid: np.ndarray, footprint: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The hidden tops of the layer's slab (:func:`~layerwatch.analysis.ledges.slab_tops`, inside ``M``) and
        the blocks with a cell on them, as the printed layer's are chosen; ``(None, None)`` when there are none."""
        lay = self.toolpath.layers
        index = int(res.layer)
        if obs.predicted is None or not 0 <= index < len(lay):
            return None, None
        earlier = slab_layers(lay, index)
        if not earlier:
            return None, None
        tops = slab_tops([self.reference(j).footprint for j in earlier], footprint)
        tops &= (working_to_top(obs.predicted.view(np.uint8), self.warper, z, photo_size) > 0) & valid
        if not tops.any():
            return None, None
        assert res.heatmap is not None
        return near_footprint(tops, res.heatmap.shape, self.topview, self.config.analysis, 0.0, valid), tops

    def _rim_objects(self, res: LayerResult, valid: np.ndarray, top_bgr: np.ndarray, footprint: np.ndarray) -> None:
        """Grey material at the layer's rim (:func:`~layerwatch.analysis.part_colour.rim_material`: an object
        on the part's edge, over the walls the scene channel leaves out) joins the change beside the printed
        layer, outside the regions already there."""
        if res.heatmap is None:
            return
        grey = rim_material(top_bgr, footprint, valid, self.config.analysis.cell_px, self.topview.px_per_mm)
        if grey is None or not grey.any():
            return
        for r in res.outside_regions:  # counted once
            box = region_box(r.bbox_mm, self.topview, grey.shape)
            if box is not None:
                grey[box] = False
        found = change_regions(grey, np.where(grey, np.float32(0.5), np.float32(1.0)), self.topview,
                               self.config.scene.min_region_mm2)
        if found:
            res.outside_regions = sorted(res.outside_regions + found, key=lambda r: -r.area_mm2)
            res.outside_anomalous_mm2 += float(sum(r.area_mm2 for r in found))

    def _frame_rejected(self, photo: np.ndarray) -> str | None:
        """The frame-quality hook (module notes): ``None`` when the frame may be analysed, else the reason."""
        if self.frame_gate is None:
            return None
        reason = self.frame_gate(photo, self.previous_photo, self.config.analysis)
        if reason is None:
            self.previous_photo = photo
        return reason

    @staticmethod
    def _error(base: dict, message: str, timings: dict, t0: float) -> LayerResult:
        res = LayerResult(status="error", message=message, **base)
        res.timings_ms = {**timings, "total": (time.perf_counter() - t0) * 1e3}
        return res


def _grown(box: tuple[float, float, float, float] | None, mm: float) -> tuple[float, float, float, float] | None:
    """``(xmin, ymin, xmax, ymax)`` grown by ``mm`` on every side (``None`` stays ``None``; a NaN ``mm`` as 0)."""
    if box is None:
        return None
    d = mm if np.isfinite(mm) else 0.0
    return (box[0] - d, box[1] - d, box[2] + d, box[3] + d)


def judge_layers(
    pipe: LayerPipeline,
    policy: PausePolicy,
    frames: Iterable[tuple[int, np.ndarray | LayerResult]],
) -> Iterator[tuple[LayerResult, Decision]]:
    """The process-and-policy loop: each layer's photo through :meth:`LayerPipeline.process`, then the policy.

    Parameters
    ----------
    pipe : LayerPipeline
    policy : PausePolicy
        Fed every result in the order of ``frames``.
    frames : iterable of (int, ndarray or LayerResult)
        ``(layer index, photo)``; a :class:`LayerResult` instead of a photo
        (one kept from an earlier run, or an unreadable photo's error) is
        judged as it is.

    Yields
    ------
    (LayerResult, Decision)
        The result (its ``decision`` and ``decision_reason`` filled in) and the policy's decision.
    """
    for index, frame in frames:
        res = frame if isinstance(frame, LayerResult) else pipe.process(frame, index)
        decision = policy.update(res)
        res.decision, res.decision_reason = decision.action, decision.reason
        yield res, decision

