"""The scene's expected appearance: what a stationary camera must see again, layer after layer.

:class:`SceneModel` keeps an *expected appearance* image ``E`` of the whole
camera view (working resolution, :mod:`layerwatch.analysis.scene_change`):

* it starts as the **empty-bed photo** taken at calibration when one is
  given (``--bed-photo``, or the one recorded with the camera), else as the
  **first accepted photo** of the series;
* for the photo of layer ``k``, the layers printed since the last accepted
  photo are projected into the image (``M_k``: each one's footprint,
  dilated by ``scene.margin_mm``, on its bottom and top planes: its top
  surface and the wall band below it). Their union with the earlier ones is
  the printed body ``P_k`` as the camera sees it; the *ledges* are the
  parts of it that show an earlier layer's top surface (each layer's
  footprint eroded by the margin, projected on its top plane, until a later
  layer covers it). Everywhere but ``M_k`` and the body's *walls* (``P_k``
  minus the ledges) the photo must match ``E`` up to a smooth illumination
  ratio (exposure, white balance, flicker, a light that moved) and noise:
  changed blocks there are the *outside anomaly* (strands, objects, a part
  that moved or detached), on the bed and on the part's lower floors.
  The photometric fit takes the pixels with no clipped channel; the change
  blocks judge a pixel with one or two clipped channels on what the clipping
  leaves known (:func:`~layerwatch.analysis.scene_change.change_blocks`), so
  a lit orange floor whose red channel clipped is still judged. ``E`` keeps
  which of its channels were clipped (:attr:`SceneModel.clipped`: it is kept
  in its own photometric frame, where a clipped 255 divided by a gain above 1
  would read as a known value). White glare is not judged.
  Inside ``M_k`` the paper's HOG comparison with the rendered reference
  judges, as before. Walls are not scored: their faces change with every
  move of the light (on the simulator, also with the part's height, by more
  than the bed's threshold), so strands hanging on a wall are left to the
  HOG channel and to later work;
* after an accepted layer, ``E`` takes the photo (mapped back into ``E``'s
  photometric frame) on the printed body, and outside it on every block
  that did not change (and is not next to a changed block): changed blocks
  keep their old appearance, so a clump that appeared at layer 12 is still
  a change at 13, 14, ... ("a failure that stays, counts") until
  :meth:`SceneModel.acknowledge` (the operator accepted it: ``E`` takes the
  current photo on the changed blocks). On a layer whose HOG comparison
  alarmed, its failing blocks keep ``E``'s old view too although the layer
  printed there (:meth:`SceneModel.hold_failing`, :mod:`layerwatch.pipeline.scene_hold`): an object on a small part
  stays a change on the next layer, when another object of the plate prints
  and the new footprint does not cover it; those *held* pixels are judged
  even on the body's walls while they stay changed. Elsewhere ``E`` is the last
  accepted photo (the issue's "photo k must match photo k-1"), which
  follows slow drift (shadows lengthening beside a growing part, a lamp
  warming up); refreshing only blocks far below the threshold left a
  patchwork of lighting states in ``E`` that itself raised false changes
  on the simulator. What it gives up: a failure that creeps in by less
  than the threshold per layer is absorbed;
* a frame that does not show the expected scene at all (black, covered,
  camera moved, light switched: gain out of range or more than
  ``scene.max_changed_share`` of the blocks changed) is **rejected**: it never
  updates ``E`` and the pipeline reports it as an error (an alert, never a
  pause). A bed photo that does not match the first frame that way, or
  whose view is shifted against it (phase correlation above
  ``MAX_SHIFT_PX``: another camera pose), is dropped (a warning) and the
  first accepted photo becomes the baseline;
  after ``REBASE_AFTER`` rejected frames in a row the current view becomes
  the baseline (the camera was moved for good: said in the result's message).

A photo of a layer that was skipped (no photo, rejected) is compared with
``M`` covering every layer printed since the last accepted one.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from layerwatch.analysis.block_masks import blocks_to_pixels
from layerwatch.analysis.cast_shadow import explained_by_shade, roof_area, shadow_zone
from layerwatch.analysis.result import LayerResult, SceneStats
from layerwatch.analysis.scene_change import (
    SATURATED,
    ChangeMap,
    change_blocks,
    change_regions,
    channel_mean,
    image_rays,
    photometric_fit,
    plane_maps,
    predicted_change,
    rays_over,
    to_working,
    top_coords,
    working_crop,
    working_size,
    working_to_top,
)
from layerwatch.analysis.settings import SceneSettings
from layerwatch.analysis.view_shift import masked_phase_shift
from layerwatch.errors import CalibrationError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.markers import detect_dots
from layerwatch.geometry.topview import TopView
from layerwatch.geometry.warp import TopViewWarper
from layerwatch.pipeline.scene_hold import held_pixels, still_held

__all__ = ["GAIN_RANGE", "REBASE_AFTER", "SceneModel", "SceneObservation", "bed_photo_pose_problem", "check_bed_photo",
           "load_bed_photo"]

#: photometric gains outside this range mean a frame that does not show the scene (dark, overexposed)
GAIN_RANGE = (0.4, 2.5)
#: whole-view shift (working px) between the bed photo and the first frame that means another pose
MAX_SHIFT_PX = 2.0
#: smaller shifts (working px) from which the bed photo is moved onto the first frame's view, and the rounds
ALIGN_SHIFT_PX = 0.1
ALIGN_ROUNDS = 4
#: rejected frames in a row after which the current view becomes the baseline (camera moved for good)
REBASE_AFTER = 3
#: spacing of the planes a roof's footprint is projected on, from the bed to the roof (what lies under it), mm
ROOF_PLANE_STEP_MM = 0.5

#: ``footprint(j) -> (top-view bool mask of layer j, z bottom, z top)``
FootprintFn = Callable[[int], "tuple[np.ndarray, float, float]"]


#: the largest float32 below :data:`SATURATED` (``cv2.inRange``'s bounds are inclusive)
_BELOW_SATURATED = float(np.nextafter(np.float32(SATURATED), np.float32(0)))


def _saturated(img: np.ndarray) -> np.ndarray:
    """Pixels with a channel at or above :data:`SATURATED`, bool (h, w) (one ``cv2.inRange`` pass)."""
    lo, hi = (-np.inf,) * img.shape[2], (_BELOW_SATURATED,) * img.shape[2]
    return cv2.inRange(img, lo, hi) == 0


def _white(img: np.ndarray) -> np.ndarray:
    """Pixels with every channel at or above :data:`SATURATED` (white glare), bool (h, w) (one ``cv2.inRange``)."""
    lo, hi = (float(SATURATED),) * img.shape[2], (np.inf,) * img.shape[2]
    return cv2.inRange(img, lo, hi) > 0


def _box(mask: np.ndarray) -> tuple[slice, slice]:
    """Rows and columns of the bounding box of a bool (h, w) mask (empty slices when nothing is set)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return slice(0, 0), slice(0, 0)
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


def _copy_where(dst: np.ndarray, src: np.ndarray, where: np.ndarray) -> None:
    """``np.copyto(dst, src, where=where[..., None])`` for (h, w, c) images and a bool (h, w) mask.

    By :func:`cv2.copyTo`, which writes into ``dst`` (a view of a larger image too) in one pass:
    ~0.03 ms where NumPy's broadcast ``where`` takes ~0.8 ms on the scene channel's box.
    Bool images are copied as their bytes.
    """
    if where.size == 0:
        return
    d = dst.view(np.uint8) if dst.dtype == bool else dst
    out = cv2.copyTo(src.view(np.uint8) if src.dtype == bool else src, np.ascontiguousarray(where).view(np.uint8), d)
    if out is not d:  # (OpenCV allocated anew: another type or layout)
        dst[...] = out.astype(dst.dtype) if dst.dtype != bool else out.view(bool)


def check_bed_photo(photo: np.ndarray | None, camera: CameraModel, name: str = "bed photo") -> np.ndarray:
    """Validate an empty-bed photo at the edge: a uint8 frame of the camera's size.

    Raises
    ------
    CalibrationError
        Unreadable (``None``) or another size than the camera's ``image_size``.
    """
    if photo is None:
        raise CalibrationError(f"{name} is not a readable image; pass the empty-bed photo taken at calibration.")
    arr = np.asarray(photo)
    w, h = camera.image_size
    if arr.dtype != np.uint8 or arr.ndim not in (2, 3) or arr.shape[:2] != (h, w):
        raise CalibrationError(f"{name} is {arr.shape[1] if arr.ndim >= 2 else '?'}x{arr.shape[0]} but the camera "
                               f"was calibrated at {w}x{h}; take the bed photo with the monitoring camera.")
    return arr


def bed_photo_pose_problem(photo: np.ndarray, camera: CameraModel, tolerance_px: float | None = None) -> str | None:
    """Whether the bed photo was taken from the camera's calibrated pose, judged by its dot markers.

    The camera's ``markers_mm`` are projected through the pose; each must have
    a detected dot within ``tolerance_px`` (default 1.5 % of the image width).
    ``None`` when they do, or when the check cannot run (no markers recorded,
    ArUco markers, fewer than three dots found: the scene model's own check
    on the first frame then decides).
    """
    if camera.markers_mm is None or camera.marker_kind != "dots" or not camera.has_pose:
        return None
    dots = np.array([b.center for b in detect_dots(photo)], float).reshape(-1, 2)
    if len(dots) < 3:
        return None
    pts = np.c_[np.asarray(camera.markers_mm, float).reshape(-1, 2), np.zeros(len(camera.markers_mm))]
    rvec, tvec = camera.pose
    uv = cv2.projectPoints(pts, rvec, tvec, camera.K, camera.dist)[0].reshape(-1, 2)
    tol = tolerance_px if tolerance_px is not None else 0.015 * camera.image_size[0]
    dist = np.linalg.norm(uv[:, None, :] - dots[None, :, :], axis=2).min(axis=1)
    if np.median(dist) > tol:
        return (f"its markers lie {np.median(dist):.0f} px from where the calibrated pose puts them "
                "(another camera position?)")
    return None


def load_bed_photo(path: str | Path | None, camera: CameraModel, *, given: bool) -> tuple[np.ndarray | None, str]:
    """Read and check the empty-bed photo for :class:`SceneModel`.

    Parameters
    ----------
    path : str or Path or None
        ``--bed-photo`` (``given=True``) or the photo recorded with the camera model.
    camera : CameraModel
    given : bool
        The user named the file: a missing or unreadable file and a wrong size
        raise. A recorded one that is missing is a warning.

    Returns
    -------
    photo : ndarray or None
        ``None`` when there is none to use (the first photo is the baseline).
    note : str
        What is missing or why the photo is not used ("" when it is).

    Raises
    ------
    CalibrationError
        A given file is missing or unreadable; any bed photo of another size than the camera's.
    """
    if path is None:
        return None, ("no empty-bed photo (take one with `layerwatch calibrate --markers bed.jpg` or pass "
                      "--bed-photo): the first photo is the scene's baseline")
    p = Path(path)
    if not p.is_file():
        if given:
            raise CalibrationError(f"bed photo {p} not found; pass the empty-bed photo taken at calibration.")
        return None, f"the bed photo recorded with the camera ({p}) is missing: the first photo is the baseline"
    photo = check_bed_photo(cv2.imread(str(p), cv2.IMREAD_COLOR), camera, name=f"bed photo {p}")
    problem = bed_photo_pose_problem(photo, camera)
    if problem is not None:
        return None, f"bed photo {p} is not used: {problem}; the first photo is the baseline"
    return photo, ""


@dataclass
class SceneObservation:
    """One photo seen by the scene model (before :meth:`SceneModel.update`).

    Attributes
    ----------
    layer : int
    image : ndarray, float32, shape (h, w, 3)
        The working image.
    predicted : ndarray, bool, shape (h, w) or None
        ``M``: where the layers printed since the last accepted photo may
        change the image (``None`` without a baseline).
    body : ndarray, bool, shape (h, w) or None
        ``P``: the whole printed body as the camera sees it, ``M`` included.
    ledges : ndarray, bool, shape (h, w) or None
        The part of ``P`` that shows earlier layers' top surfaces (scored outside ``M``).
    hidden_ledges : ndarray, bool, shape (h, w) or None
        Earlier layers' top surfaces inside ``M``: lower floors that no earlier
        photo of the series showed (in single-photo mode all of them), so the
        change beside the print cannot judge them; the reference's HOG does
        (:func:`~layerwatch.analysis.ledges.ledge_regions`).
    change : ChangeMap or None
        Changed blocks outside ``M`` (``None`` without a baseline).
    ratio : ndarray, float32, shape (h, w, 3) or None
        ``photo ~ ratio * E`` (:func:`~layerwatch.analysis.scene_change.photometric_fit`).
    gain : ndarray, shape (3,) or None
        The frame's median ratio per channel.
    rejected : str or None
        Why the frame does not show the expected scene (it must not update ``E``).
    baseline : str
        ``"bed photo"``, ``"first photo"`` or ``""`` (this photo will be the baseline).
    note : str
        A warning for the result's message (bed photo dropped, re-based).
    held : ndarray, bool, shape (h, w) or None
        Pixels where ``E`` keeps its old view although the layer printed there: the failing blocks of a
        layer whose comparison alarmed (:meth:`SceneModel.hold_failing`); ``None``: none.
    printed : tuple of two ndarray, bool, shape (h, w), or None
        A baseline photo taken after layer ``layer >= 0`` (a monitor that joined a print under way, or a
        view re-based): the body ``P`` and its ledges of layers ``0..layer``, which the photo shows and
        the next comparisons must know (else the part's walls are scored as the scene beside it).
    ms : float
    """

    layer: int
    image: np.ndarray
    predicted: np.ndarray | None = None
    body: np.ndarray | None = None
    ledges: np.ndarray | None = None
    hidden_ledges: np.ndarray | None = None
    change: ChangeMap | None = None
    ratio: np.ndarray | None = None
    gain: np.ndarray | None = None
    rejected: str | None = None
    baseline: str = ""
    note: str = ""
    held: np.ndarray | None = None
    printed: tuple[np.ndarray, np.ndarray] | None = None
    ms: float = 0.0

    def stats(self) -> SceneStats:
        """The typed figures for :attr:`LayerResult.scene`."""
        c = self.change
        g = self.gain if self.gain is not None else np.ones(3)
        return SceneStats(baseline=self.baseline, threshold=float(c.threshold) if c else 0.0,
                          noise=float(c.noise) if c else 0.0, blocks_scored=int(c.scored.sum()) if c else 0,
                          blocks_changed=int(c.changed.sum()) if c else 0,
                          gain=(round(float(g[0]), 4), round(float(g[1]), 4), round(float(g[2]), 4)),
                          ms=round(self.ms, 3))


@dataclass(frozen=True)
class _AckPatch:
    """The pixels of ``E`` that :meth:`SceneModel.acknowledge` sets, and their values.

    Attributes
    ----------
    rows, cols : slice
        Their bounding box in ``E`` (:attr:`SceneModel.box` coordinates).
    where : ndarray, bool, shape (r, c)
        The pixels in it.
    values : ndarray, float32, shape (k, 3)
        The accepted photo in ``E``'s photometric frame at those pixels.
    clipped : ndarray, bool, shape (k, 3)
        Its channels the camera clipped there (:attr:`SceneModel.clipped`).
    """

    rows: slice
    cols: slice
    where: np.ndarray
    values: np.ndarray
    clipped: np.ndarray


def _working_px_per_mm(mx: np.ndarray, observed: np.ndarray, topview: TopView) -> float:
    """Working-image px per mm on the bed, along the image rows (the view's median; 0 when nothing is observed).

    ``mx`` is the top-view column of every working pixel's ray on the bed (:func:`top_coords` at 0):
    its step from one column to the next is top-view px per working px. Across the image rows a
    camera at ~45 deg sees the bed least foreshortened, so this is the larger of the view's two scales.
    """
    step = np.abs(np.diff(mx, axis=1))[observed[:, 1:] & observed[:, :-1]]
    if step.size == 0:
        return 0.0
    return float(topview.px_per_mm / max(float(np.median(step)), 1e-6))


class SceneModel:
    """The expected appearance ``E`` of the camera view and its update rule (module notes).

    Parameters
    ----------
    camera : CameraModel
        Posed camera of the photos.
    topview : TopView
        The observed square (the scene channel looks at its image on the bed).
    settings : SceneSettings
    bed_photo : ndarray, optional
        Empty-bed photo of the same camera and pose (:func:`check_bed_photo`).
    reach_mm : (float, float, float, float), optional
        ``(xmin, ymin, xmax, ymax)`` of the bed where the job puts material (beads included), mm;
        with ``top_z_mm`` (the highest layer, mm) the plane maps are kept only for the pixels
        whose ray can meet it (:attr:`reach_box`). Without them, for the whole :attr:`box`.
    top_z_mm : float, optional
    """

    def __init__(self, camera: CameraModel, topview: TopView, settings: SceneSettings | None = None,
                 bed_photo: np.ndarray | None = None, *,
                 reach_mm: tuple[float, float, float, float] | None = None, top_z_mm: float | None = None) -> None:
        self.camera, self.topview = camera, topview
        self.settings = settings or SceneSettings()
        self.size = working_size(camera.image_size, self.settings.working_px)
        A, B = plane_maps(image_rays(camera, self.size), camera.center_mm, topview)
        mx, my = top_coords((A, B), 0.0)
        H, W = topview.shape
        #: working-image pixels that see the observed square on the bed
        self.observed = (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
        #: the bounding box of :attr:`observed` (rows, columns): ``E`` is kept on it only
        self.box = _box(self.observed)
        #: the part of :attr:`box` whose rays can meet the printed material (predicted change is
        #: nowhere else): the plane maps are kept on it only
        self.reach_box = self._reach_box(A, B, reach_mm, top_z_mm)
        #: :func:`plane_maps` on :attr:`reach_box`
        self.maps = (np.ascontiguousarray(A[:, self.reach_box[0], self.reach_box[1]]),
                     np.ascontiguousarray(B[:, self.reach_box[0], self.reach_box[1]]))
        #: working-image px per mm on the bed across the view (the larger of its two scales, at the view's
        #: median): how far a cast shadow may reach in the image (:mod:`layerwatch.analysis.cast_shadow`);
        #: 0 when that test is off (``shadow_reach`` 0: nothing reads it, so a new print does not pay for it)
        self.px_per_mm = _working_px_per_mm(mx, self.observed, topview) if self.settings.shadow_reach > 0 else 0.0
        self.reset(bed_photo)

    def _reach_box(self, A: np.ndarray, B: np.ndarray, reach_mm: tuple[float, float, float, float] | None,
                   top_z_mm: float | None) -> tuple[slice, slice]:
        """Rows and columns of :attr:`box` with a pixel whose ray, between 1 mm below the bed and 1 mm above
        ``top_z_mm``, passes over ``reach_mm`` grown by the margin and 2 px (:attr:`box` when not given).

        :func:`~layerwatch.analysis.scene_change.rays_over` keeps a superset of the pixels that can see
        material, so :func:`predicted_change` is False outside the box as on the box.
        """
        rows, cols = self.box
        if reach_mm is None or top_z_mm is None or not np.all(np.isfinite([*reach_mm, top_z_mm])):
            return self.box
        pad = abs(self.settings.margin_mm) + 2.0 / self.topview.px_per_mm + 1.0
        (u0, v0), (u1, v1) = self.topview.to_px(np.array([[reach_mm[0] - pad, reach_mm[1] - pad],
                                                          [reach_mm[2] + pad, reach_mm[3] + pad]], float))
        keep = rays_over((A[:, rows, cols], B[:, rows, cols]), (u0, v0, u1, v1), -1.0, top_z_mm + 1.0)
        r, c = _box(keep)
        if r.stop == 0:
            return slice(0, 0), slice(0, 0)
        return slice(rows.start + r.start, rows.start + r.stop), slice(cols.start + c.start, cols.start + c.stop)

    def reset(self, bed_photo: np.ndarray | None = None) -> None:
        """Start a new print: ``E`` is the bed photo when given, else the next accepted photo."""
        self.expected: np.ndarray | None = None
        #: the channels of ``E`` that the camera clipped in the photo they came from (bool, shape of ``E``):
        #: their value is only a lower bound (``E`` is kept in its own photometric frame, so a clipped
        #: 255 divided by a gain above 1 no longer reads as clipped)
        self.clipped: np.ndarray | None = None
        self.baseline = ""
        self.last_layer = -1
        #: the printed body seen so far (``P``) and its ledges, on :attr:`reach_box` (nowhere else), and the
        #: last layer in it
        self.body = np.zeros(self.maps[0].shape[1:], bool)
        self.ledges = np.zeros(self.maps[0].shape[1:], bool)
        self.body_layer = -1
        self._confirmed = False
        self._rejections = 0
        self._ack: _AckPatch | None = None
        #: working-image pixels (bool, full working size) of a failure that stays: ``E`` keeps its old view
        #: there and they are judged even on the body's walls (:meth:`hold_failing`); ``None``: none
        self.held: np.ndarray | None = None
        #: what the camera sees under the part's roofs so far (bridges, overhangs, lintels: material printed over
        #: air), on :attr:`reach_box`: a shade may cover whole blocks there
        #: (:mod:`layerwatch.analysis.cast_shadow`); kept only with ``shadow_reach`` > 0
        self.roofs = np.zeros(self.maps[0].shape[1:], bool)
        #: the last layer whose footprint :meth:`_add_roof` saw, and that footprint (the next layer's "below"),
        #: as bits (np.packbits: 45 kB at 600 x 600 px instead of 360 kB held between layers)
        self._below: tuple[int, np.ndarray] | None = None
        if bed_photo is not None:
            self.expected = self._crop(to_working(check_bed_photo(bed_photo, self.camera), self.size))
            self.clipped = self.expected >= SATURATED
            self.baseline = "bed photo"

    def _crop(self, image: np.ndarray) -> np.ndarray:
        """A working image (h, w, 3) on :attr:`box`, a contiguous copy: how ``E`` is stored."""
        return np.ascontiguousarray(image[self.box]).copy()

    def _expected_full(self) -> np.ndarray:
        """``E`` as a working-size image (h, w, 3), 0 outside :attr:`box` (a per-photo temporary).

        Nothing outside the box is observed, so nothing there is fitted or scored
        (:func:`photometric_fit` and :func:`change_blocks` weigh such pixels by 0).
        """
        assert self.expected is not None
        full = np.zeros((self.size[1], self.size[0], 3), np.float32)
        full[self.box] = self.expected
        return full

    def _clipped_full(self) -> np.ndarray:
        """:attr:`clipped` as a working-size bool mask (h, w, 3), False outside :attr:`box`."""
        assert self.clipped is not None
        full = np.zeros((self.size[1], self.size[0], 3), bool)
        full[self.box] = self.clipped
        return full

    def _full(self, mask: np.ndarray) -> np.ndarray:
        """A bool mask on :attr:`reach_box` as a working-size one (False elsewhere)."""
        out = np.zeros(self.observed.shape, bool)
        out[self.reach_box] = mask
        return out

    def _predicted(self, footprint: np.ndarray, z_planes: np.ndarray, margin_mm: float,
                   planes: dict[float, tuple[np.ndarray, np.ndarray]] | None = None) -> np.ndarray:
        """:func:`predicted_change` as a working-size bool mask (False outside :attr:`box`); ``planes``:
        its ``coords`` (the planes' coordinates shared between the calls of one photo)."""
        out = np.zeros(self.observed.shape, bool)
        if self.maps[0].size == 0:  # the camera does not see the observed square (or the print) at all
            return out
        out[self.reach_box] = predicted_change(footprint, z_planes, self.maps, self.topview, margin_mm, planes)
        return out

    # ------------------------------------------------------------ per photo
    def observe(self, photo: np.ndarray, layer: int, footprints: FootprintFn,
                plan: FootprintFn | None = None) -> SceneObservation:
        """Compare the photo of layer ``layer`` with ``E`` outside the predicted change.

        ``footprints(j)`` gives the top-view footprint of layer ``j`` and its
        bottom and top heights (the pipeline's references); it is called for
        every layer printed since the last accepted photo. ``plan(j)`` gives the
        same without rendering (:func:`~layerwatch.render.mask.gcode_mask`): a
        baseline photo of a print under way takes the body of every layer before
        it from it (default: ``footprints``).
        """
        t0 = time.perf_counter()
        if self.expected is None:  # a baseline is judged on the whole frame
            obs = SceneObservation(int(layer), to_working(photo, self.size), baseline=self.baseline)
            self._judge_baseline(obs, plan or footprints)
        else:
            obs = SceneObservation(int(layer), self._working(photo), baseline=self.baseline)
            self._compare(obs, footprints, plan)
            if obs.rejected and self.baseline == "bed photo" and not self._confirmed:
                obs.note = (f"the bed photo does not match this camera view ({obs.rejected}); "
                            "the first photo is the baseline instead")
                self._rebase(obs, photo, plan or footprints)
            elif obs.rejected:
                self._rejections += 1
                if self._rejections >= REBASE_AFTER:
                    obs.note = (f"{self._rejections} frames in a row did not match the scene: the current view "
                                "is the new baseline (camera moved?)")
                    self._rebase(obs, photo, plan or footprints)
        obs.ms = (time.perf_counter() - t0) * 1e3
        return obs

    def _rebase(self, obs: SceneObservation, photo: np.ndarray, footprints: FootprintFn) -> None:
        """Drop the baseline: ``obs`` (its comparison undone) is judged as the next one, on the whole frame."""
        self.expected, self.clipped, self.baseline, obs.baseline = None, None, "", ""
        obs.predicted = obs.change = None
        obs.image = to_working(photo, self.size)
        self._judge_baseline(obs, footprints)

    def _working(self, photo: np.ndarray) -> np.ndarray:
        """The working image as a comparison with ``E`` reads it: :func:`to_working` on :attr:`box`, 0 elsewhere.

        Nothing outside the box is observed, so nothing there is fitted or scored (as for ``E``,
        :meth:`_expected_full`); resizing and blurring only the box (and the blur's reach) gives its
        pixels bit for bit (:func:`~layerwatch.analysis.scene_change.working_crop`), for ~40 % of the
        cost on a bed that fills a third of the view.
        """
        crop, (y0, x0) = working_crop(photo, self.size, self.box)
        w, h = self.size
        if crop.shape[:2] == (h, w):  # the whole image (the box reaches the bottom or right edge)
            return crop
        out = np.zeros((h, w, 3), np.float32)
        rows, cols = self.box
        out[rows, cols] = crop[rows.start - y0:rows.stop - y0, cols.start - x0:cols.stop - x0]
        return out

    @staticmethod
    def _unusable_baseline(image: np.ndarray) -> str | None:
        grey = channel_mean(image)
        if grey.mean() < 12 or grey.std() < 3 or (grey >= SATURATED).mean() > 0.5:
            return "the frame is too dark, flat or overexposed to be the scene's baseline"
        return None

    def _compare(self, obs: SceneObservation, footprints: FootprintFn, plan: FootprintFn | None = None) -> None:
        st = self.settings
        assert self.expected is not None, "_compare runs only with a baseline"
        E = self._expected_full()
        first = self.body_layer + 1 if self.body_layer < obs.layer else obs.layer
        predicted, ledges, z_top = self._printed(first, obs, footprints, plan=plan)
        obs.predicted, obs.body, obs.ledges = predicted, self._full(self.body) | predicted, ledges
        img = obs.image
        walls = obs.body & ~ledges
        if self.held is not None:  # a failure that stays is judged where it is, walls included
            walls &= ~self.held
        # (nothing outside the box is observed): the fit needs every channel; the change blocks judge a
        # pixel with a clipped channel on what the clipping leaves known (a bright orange floor's red channel
        # clips under a lamp, its green and blue still show an object), all but white glare
        usable, scored = np.zeros(self.observed.shape, bool), np.zeros(self.observed.shape, bool)
        b = self.box
        assert self.clipped is not None
        scored[b] = self.observed[b] & ~predicted[b] & ~walls[b]
        c = self.clipped  # (element-wise: numpy's reduction over a 3-long axis is slow)
        usable[b] = scored[b] & ~_saturated(img[b]) & ~(c[..., 0] | c[..., 1] | c[..., 2])
        if self.held is not None:  # not a light reference: it was a failure at the last photo
            usable[b] &= ~self.held[b]
        scored[b] &= ~_white(img[b]) & ~(c[..., 0] & c[..., 1] & c[..., 2])
        if self.baseline == "bed photo" and not self._confirmed:
            shift = self._shift(img, E, usable)
            if shift is not None:
                obs.rejected = shift
                return
            E = self._align_bed_photo(obs, img, E, usable)
        obs.ratio, obs.gain = photometric_fit(img, E, usable)
        if np.any(obs.gain < GAIN_RANGE[0]) or np.any(obs.gain > GAIN_RANGE[1]):
            obs.rejected = (f"the frame does not show the expected scene (photometric gain "
                            f"{', '.join(f'{g:.2f}' for g in obs.gain)}: dark, covered or overexposed?)")
            return
        clipped = self._clipped_full()
        obs.change = change_blocks(img, E, scored, obs.ratio, st, expected_clipped=clipped)
        if st.shadow_reach > 0 and obs.change.changed.any():  # the part's own cast shadow is light, not material
            zone = shadow_zone(obs.body, st.shadow_reach * z_top * self.px_per_mm)
            shaded = explained_by_shade(obs.change, img, np.minimum(E * obs.ratio, 255.0), scored, zone, clipped,
                                        self._full(self.roofs) if self.roofs.any() else None)
            if shaded.any():
                obs.change = replace(obs.change, changed=obs.change.changed & ~shaded)
        share = obs.change.changed_share
        if share > st.max_changed_share:
            obs.rejected = (f"{share:.0%} of the view beside the print changed: camera moved or covered, "
                            "or the light changed")

    def _printed(self, first: int, obs: SceneObservation, footprints: FootprintFn,
                 ledges: np.ndarray | None = None, plan: FootprintFn | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """Where layers ``first..obs.layer`` may change the image (``M``), the ledges then in view, and the top.

        Returns ``(predicted, ledges, z_top)``: bool (h, w) working images (the ledges grow from ``ledges``,
        by default the model's own) and the highest layer top among them, mm; sets ``obs.hidden_ledges``
        (the lower floors inside ``M``) and adds the layers' roofs (:meth:`_add_roof`, with
        ``shadow_reach`` > 0). The layers before ``obs.layer`` take their footprints from ``plan`` when
        given (the same masks: a frame after skipped layers renders none of them, and the renderer's
        stack, already at ``obs.layer``, is not started again from the first layer for them).
        """
        st = self.settings
        earlier = footprints if plan is None else plan
        predicted = np.zeros(self.observed.shape, bool)
        ledges = self._full(self.ledges) if ledges is None else ledges
        planes: dict[float, tuple[np.ndarray, np.ndarray]] = {}  # the planes' top-view coordinates, computed once
        z_top = 0.0
        for j in range(first, obs.layer + 1):
            fp, z0, z1 = (footprints if j == obs.layer else earlier)(j)
            z_top = max(z_top, float(z1))
            if st.shadow_reach > 0:
                self._add_roof(j, fp, float(z0), earlier)
            planes = {z: c for z, c in planes.items() if z == float(z0)}  # (the last layer's top: this one's bottom)
            band = self._predicted(fp, np.array([z0, z1]), st.margin_mm, planes)
            predicted |= band
            ledges &= ~band
            if j == obs.layer:  # lower floors inside M: no earlier photo of this series showed them
                obs.hidden_ledges = ledges & predicted
            ledges |= self._predicted(fp, np.array([z1]), -st.margin_mm, planes)
        return predicted, ledges, z_top

    def _judge_baseline(self, obs: SceneObservation, footprints: FootprintFn) -> None:
        """Whether ``obs`` can be the baseline (``obs.rejected``), and, a usable photo of a print under way
        (``obs.layer >= 0``), the body and ledges of every layer printed so far into ``obs.printed`` (the photo
        shows them: later comparisons leave the body's walls out of the scene and take its ledges as floors,
        as a model that watched from layer 0 does)."""
        obs.rejected = self._unusable_baseline(obs.image)
        if obs.rejected is not None or obs.layer < 0 or self.observed.size == 0:
            return
        predicted, ledges, _ = self._printed(0, obs, footprints, np.zeros(self.observed.shape, bool))
        obs.hidden_ledges = None  # (no comparison: nothing inside M is judged on this photo)
        obs.printed = (predicted, ledges)

    def _add_roof(self, j: int, footprint: np.ndarray, z0: float, footprints: FootprintFn) -> None:
        """Add what the camera sees under layer ``j``'s roof (:func:`~layerwatch.analysis.cast_shadow.roof_area`
        against layer ``j - 1``) to :attr:`roofs`: the roof's footprint, grown by the margin, projected on
        planes every :data:`ROOF_PLANE_STEP_MM` from the bed up to the layer's bottom ``z0`` (whatever
        floor lies under it)."""
        below = (np.unpackbits(self._below[1], count=footprint.size).view(bool).reshape(footprint.shape)
                 if self._below is not None and self._below[0] == j - 1 else (footprints(j - 1)[0] if j > 0 else None))
        self._below = (j, np.packbits(footprint))
        if below is None or z0 <= 0 or self.maps[0].size == 0:
            return
        roof = roof_area(footprint, below, self.settings.margin_mm, self.topview.px_per_mm)
        if roof.any():
            planes = np.append(np.arange(0.0, z0, ROOF_PLANE_STEP_MM), z0)
            self.roofs |= predicted_change(roof, planes, self.maps, self.topview, self.settings.margin_mm)

    @staticmethod
    def _view_shift(img: np.ndarray, E: np.ndarray, usable: np.ndarray) -> tuple[float, float] | None:
        """Shift ``(dx, dy)`` of the photo's usable area against ``E``, working px (phase correlation);
        None where the area is too small, dark or flat to tell."""
        # dark, flat or hidden (None): the gain check decides; the print is not part of the bed photo
        return masked_phase_shift(channel_mean(img), channel_mean(E), usable, min_std=3.0)

    @classmethod
    def _shift(cls, img: np.ndarray, E: np.ndarray, usable: np.ndarray) -> str | None:
        """Why the baseline is not this camera view (shift of the usable area above ``MAX_SHIFT_PX``), or ``None``."""
        d = cls._view_shift(img, E, usable)
        if d is not None and np.hypot(*d) > MAX_SHIFT_PX:
            return f"the view is shifted by ({d[0]:.0f}, {d[1]:.0f}) working px against it: another camera pose"
        return None

    def _align_bed_photo(self, obs: SceneObservation, img: np.ndarray, E: np.ndarray, usable: np.ndarray) -> np.ndarray:
        """Move the bed photo (``E``) onto the first frame's view when the mount flexed by less than
        ``MAX_SHIFT_PX`` since it was taken; returns ``E`` as a working-size image (moved or not).

        Phase correlation of masked, windowed images underestimates a sub-pixel shift, so it is
        measured again on the moved photo, :data:`ALIGN_ROUNDS` times at most.
        """
        total = np.zeros(2)
        base = self.expected
        assert base is not None, "aligned only against a bed photo"
        for _ in range(ALIGN_ROUNDS):
            d = self._view_shift(img, E, usable)
            if d is None or np.hypot(*d) < ALIGN_SHIFT_PX:
                break
            total += d
            self.expected = cv2.warpAffine(base, np.array([[1, 0, total[0]], [0, 1, total[1]]], np.float32),
                                           base.shape[1::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            self.clipped = self.expected >= SATURATED
            E = self._expected_full()
        if total.any():
            obs.note = f"bed photo moved onto this camera view by ({total[0]:.2f}, {total[1]:.2f}) working px"
        return E

    def update(self, obs: SceneObservation) -> None:
        """Accept the photo after its layer was analysed: ``E`` takes it inside ``M`` only.

        A rejected observation changes nothing. Without a baseline the photo becomes ``E``.
        """
        if obs.rejected is not None:
            return
        self._rejections = 0
        self._ack = None
        if self.expected is None:
            self.expected, self.baseline = self._crop(obs.image), "first photo"
            self.clipped = self.expected >= SATURATED
            if obs.printed is not None:  # a print under way: its body is in the photo, and known
                self.body, self.ledges = obs.printed[0][self.reach_box].copy(), obs.printed[1][self.reach_box].copy()
        elif obs.body is not None:
            assert obs.predicted is not None and obs.ledges is not None  # set with obs.body by _compare
            take = obs.predicted | (obs.body & ~obs.ledges) | self._quiet(obs)
            changed = obs.change.pixels(obs.image.shape[:2]) if obs.change is not None and self.held is not None else None
            held = still_held(self.held, obs.held, obs.predicted, changed)
            if held is not None:  # a failure the comparison found where the layer printed stays a change
                take &= ~held
            self.held = held
            take = take[self.box]
            rows, cols = _box(take)  # the division only where E takes the photo (E's own coordinates)
            r0, c0 = self.box[0].start, self.box[1].start
            img_box = (slice(rows.start + r0, rows.stop + r0), slice(cols.start + c0, cols.stop + c0))
            _copy_where(self.expected[rows, cols], self._in_expected_frame(obs, img_box), take[rows, cols])
            assert self.clipped is not None
            _copy_where(self.clipped[rows, cols], obs.image[img_box] >= SATURATED, take[rows, cols])
            self._ack = self._ack_patch(obs)
            self._confirmed = True
            self.body, self.ledges = obs.body[self.reach_box].copy(), obs.ledges[self.reach_box].copy()
            self.body_layer = max(self.body_layer, obs.layer)
        self.last_layer = max(self.last_layer, obs.layer) if obs.body is not None else obs.layer
        if obs.body is None:  # this photo is the baseline: what it shows is the scene (the body included)
            self.body_layer = obs.layer

    def _quiet(self, obs: SceneObservation) -> np.ndarray:
        """Working-image pixels outside ``P`` of scored blocks that did not change and do not touch a change."""
        c = obs.change
        if c is None or obs.predicted is None:
            return np.zeros(obs.image.shape[:2], bool)
        near = cv2.dilate(c.changed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        quiet = ChangeMap(c.score, c.scored, c.scored & ~c.changed & ~near, c.threshold,
                          c.noise, c.block_px)
        return quiet.pixels(obs.image.shape[:2]) & self.observed & ~obs.predicted

    @staticmethod
    def _in_expected_frame(obs: SceneObservation, box: tuple[slice, slice] = (slice(None), slice(None))) -> np.ndarray:
        """The photo mapped into ``E``'s photometric frame (``image / ratio``), on ``box`` of the working image."""
        assert obs.ratio is not None  # set by photometric_fit before any photo is accepted into E
        return obs.image[box] / np.maximum(obs.ratio[box], 1e-3)

    def _ack_patch(self, obs: SceneObservation) -> _AckPatch | None:
        """What :meth:`acknowledge` writes into ``E`` for the accepted ``obs``: its changed blocks (grown by a
        block) and its held pixels (:meth:`hold_failing`) on the observed pixels, in ``E``'s photometric
        frame; ``None`` when nothing changed or was held.

        Kept instead of the observation itself: a few changed blocks, not two working-size images.
        """
        c = obs.change
        held = self.held  # set by update() just before
        if (c is None or not c.changed.any()) and held is None:
            return None
        px = np.zeros(obs.image.shape[:2], bool)
        if c is not None and c.changed.any():
            blocks = c.pixels(obs.image.shape[:2]).astype(np.uint8)
            b = c.block_px
            px = cv2.dilate(blocks, np.ones((2 * b + 1, 2 * b + 1), np.uint8)).astype(bool)
        if held is not None:
            px |= held
        px = (px & self.observed)[self.box]
        rows, cols = _box(px)
        r0, c0 = self.box[0].start, self.box[1].start
        img_box = (slice(rows.start + r0, rows.stop + r0), slice(cols.start + c0, cols.stop + c0))
        where = px[rows, cols]
        return _AckPatch(rows, cols, where, self._in_expected_frame(obs, img_box)[where],
                         obs.image[img_box][where] >= SATURATED)

    def acknowledge(self) -> int:
        """The operator accepted what changed: ``E`` takes the last accepted photo on its changed blocks.

        Returns
        -------
        int
            Working-image pixels updated (0 when nothing was changed).
        """
        patch, self._ack = self._ack, None
        self.held = None
        if patch is None or self.expected is None:
            return 0
        self.expected[patch.rows, patch.cols][patch.where] = patch.values
        if self.clipped is not None:
            self.clipped[patch.rows, patch.cols][patch.where] = patch.clipped
        return int(patch.where.sum())

    def hold_failing(self, obs: SceneObservation, failing_top: np.ndarray, z: float) -> int:
        """Keep ``E``'s old view on a failure the HOG comparison found where the layer printed
        (:mod:`layerwatch.pipeline.scene_hold`): its pixels keep their old appearance when :meth:`update`
        takes the photo, so the scene channel still sees the failure as a change beside the print while it
        stays, until a later layer prints over it or the operator acknowledges it (:meth:`acknowledge`).

        Parameters
        ----------
        obs : SceneObservation
            The layer's observation, before :meth:`update`.
        failing_top : ndarray, bool, shape of the top view
            The failing blocks (:func:`~layerwatch.pipeline.scene_hold.failing_blocks`) on the layer's plane.
        z : float
            Height of that plane, mm.

        Returns
        -------
        int
            Working-image pixels held (0 without a baseline or failing blocks in view).
        """
        if obs.predicted is None or self.maps[0].size == 0 or not np.any(failing_top):
            return 0
        held = held_pixels(failing_top, z, self.maps, self._full, self.observed)
        obs.held = held if obs.held is None else (obs.held | held)
        return int(held.sum())

    # ------------------------------------------------------------ reporting
    def fill_result(self, res: LayerResult, obs: SceneObservation, warper: TopViewWarper, z: float,
                    photo_size: tuple[int, int], valid: np.ndarray | None) -> None:
        """Put the observation's outside anomaly (top view of plane ``z``, bed mm) into ``res``.

        The changed blocks are warped with the pipeline's own top-view warp
        (the same homography and lens model as the photo), so regions are in
        the bed coordinates of the layer plane like the HOG regions.
        """
        res.scene = obs.stats()
        if obs.note:
            res.message = f"{res.message}; {obs.note}" if res.message else obs.note
        c = obs.change
        if c is None or not c.changed.any():
            return
        h, w = obs.image.shape[:2]
        sim = np.where(c.changed, np.minimum(1.0, c.threshold / np.maximum(c.score, 1e-6)), 1.0)
        code = np.where(c.changed, 1 + np.round(sim * 250), 0).astype(np.uint8)
        top = working_to_top(blocks_to_pixels(code, c.block_px, (h, w)), warper, z, photo_size)
        changed = top > 0
        if valid is not None:
            changed &= valid
        sim_top = np.where(changed, (top.astype(np.float32) - 1) / 250.0, 1.0).astype(np.float32)
        regions = change_regions(changed, sim_top, self.topview, self.settings.min_region_mm2)
        res.outside_regions = regions
        res.outside_anomalous_mm2 = float(sum(r.area_mm2 for r in regions))
