"""Virtual camera photos of a print after each layer, with injected failures.

How the simulated photo differs from the reference renderer (``render.fast``)
------------------------------------------------------------------------------
The reference is an orthographic *top view* of the ideal layer drawn by the
reference renderer's own bead raster and light model. The simulator shares
none of that code path:

1. **Geometry.** It builds its own 3-D height field of the *whole printed part*
   (all layers so far, not one layer) on a bed-aligned grid (8 px/mm by
   default) with :mod:`layerwatch.simulate.raster`, plus per cell the empty
   interval left under a bead printed over nothing (a bridge, an overhang,
   the lintel over a window: more than ``2.5`` layers of air under it; the
   tallest one per cell), which the camera's rays pass through; every bead is a capsule with
   an elliptical cross-section, and each bead gets random width (6 %), position
   (0.02 mm) and height (0.01 mm) jitter plus a sinusoidal extrusion-rate
   wobble along its length, so clean layers are never pixel-identical to the
   reference. Failures edit this geometry (removed/thinned segments, shifted
   layers, displaced/tilted part (or one object of a plate: ``Failure.within_mm``), objects and draped strands with their own
   height).
2. **Projection.** The photo is a *perspective camera view* (OpenCV pinhole +
   radial distortion, pose at ~45 degrees): every camera pixel's ray is marched
   through the height field (:mod:`layerwatch.simulate.shade`), so walls,
   occlusion and the parallax of tall layers are physically right — warping
   the photo with the homography of the top layer's plane aligns the top layer
   only.
3. **Appearance.** Blinn-Phong shading under a spot light beside the camera
   plus an overhead fill, a cavity/ambient-occlusion term, specular highlights,
   layer lines on walls, a coloured filament, a procedural textured bed with
   white dot markers (beyond the part) and a dark background.
4. **Sensor.** Per-frame light position and intensity jitter, slow exposure and
   white-balance drift, vignetting, Gaussian blur (0.5-1.1 px), shot and read
   noise, gamma and 8-bit quantisation.

Frames are BGR ``uint8`` (as ``cv2.imread`` returns). Ground-truth masks are
in the *top view of the top layer's plane* and hold what the camera sees of the
failure in the whole scene after the layer (:mod:`layerwatch.simulate.truth`):
the holes of a patch (``infill_defect``, ``thin_wall``) still open, the moved
part or shifted layers as seen plus the places they left (``detachment``,
``layer_shift``), the object or strands where no part hides them
(``foreign_body``, ``spaghetti``); for ``nothing_extruded`` the footprint of
the layer that was not printed (no material is deposited on the layers where
it is active).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Sequence

import cv2
import numpy as np

from layerwatch.errors import CalibrationError, ConfigError
from layerwatch.gcode.toolpath import Toolpath, part_mask
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.simulate import failures as fl
from layerwatch.simulate import truth as tr
from layerwatch.simulate.frame import SimFrame, save_frame
from layerwatch.simulate.photo import Photographer
from layerwatch.simulate.raster import grid_params, solid_area, stamp_capsules
from layerwatch.simulate.settings import SimSettings

__all__ = ["SimFrame", "PrintSimulator", "save_frame", "simulate_layer", "simulate_print"]


_GAP_LAYERS = 2.5  # air under a new bead (layers) that makes a gap the rays pass through
_TILT_ARM_MM = 25.0  # a detached part pivots about a line this far behind its centre


def _clip_disc(p0, p1, c, R):
    """Parameter interval ``[ti, to]`` of each segment inside the disc (ti >= to: none)."""
    d = p1 - p0
    f = p0 - c
    a = np.maximum((d * d).sum(1), 1e-12)
    b = 2 * (f * d).sum(1)
    cc = (f * f).sum(1) - R * R
    disc = b * b - 4 * a * cc
    sq = np.sqrt(np.maximum(disc, 0))
    ti = np.clip((-b - sq) / (2 * a), 0, 1)
    to = np.clip((-b + sq) / (2 * a), 0, 1)
    to = np.where(disc > 0, to, ti)
    return ti, to


class PrintSimulator:
    """Incremental simulator of one print (height field kept between frames).

    Parameters
    ----------
    toolpath : Toolpath
    camera : CameraModel
        With a pose; its ``image_size`` is the photo size.
    topview : TopView
        Frame of the truth masks.
    failures : sequence of Failure, or a Scenario
    seed : int
        Seed of print imperfections and camera effects.
    settings : SimSettings, optional
    """

    def __init__(
        self,
        toolpath: Toolpath,
        camera: CameraModel,
        topview: TopView,
        failures: Sequence[fl.Failure] | fl.Scenario = (),
        seed: int = 0,
        settings: SimSettings | None = None,
    ) -> None:
        if not camera.has_pose:
            raise CalibrationError("the simulator needs a camera with a pose; use default_camera().")
        if toolpath.n_layers == 0:
            raise ConfigError("the toolpath has no layers to simulate; check the G-code.")
        self.tp, self.camera, self.topview = toolpath, camera, topview
        self.settings = settings or SimSettings()
        self.seed = int(seed)
        if isinstance(failures, fl.Scenario):
            failures = failures.failures
        self.failures = [fl.resolve(f, toolpath) for f in failures]
        st = self.settings
        m = st.grid_margin_mm
        self.grid = TopView(st.grid_px_per_mm, topview.width_mm + 2 * m, topview.height_mm + 2 * m,
                            topview.center_mm)
        self.gp = grid_params(self.grid)
        if st.renderer == "blender":  # Blender Cycles for the scene's radiance (simulate/photoreal.py)
            from layerwatch.simulate.photoreal import BlenderPhotographer

            self.cam: Photographer = BlenderPhotographer(camera, topview, self.grid, st, self.seed)
        else:
            self.cam = Photographer(camera, topview, self.grid, st, self.seed)
        self.C = self.cam.C
        self._reset()

    # ---------------------------------------------------------------- set-up
    def _reset(self) -> None:
        self.h = np.zeros(self.grid.shape, np.float32)
        self.mat = np.zeros(self.grid.shape, np.uint8)
        #: per cell the empty interval (lo, hi) mm under printed material (hi = 0: none)
        self.gap = np.zeros((*self.grid.shape, 2), np.float32)
        self.hf, self.matf = self.h.copy(), self.mat.copy()  # skirt: never detaches
        self.has_fixed = False
        self.next_layer = 0
        #: per layer-shift failure (index in ``failures``) the part's height field before its onset
        self.before_shift: dict[int, np.ndarray] = {}

    # -------------------------------------------------------------- geometry
    def layer_segments(self, i: int):
        """Actual beads of layer ``i``: ``(p0, p1, w, scale, removed, skirt)``.

        ``skirt`` flags beads not attached to the part (skirt/brim lines), which
        stay put when the part detaches. ``removed`` maps the index of a patch failure to ``(p0, p1, w)`` of the
        pieces it removed or under-extruded (nominal geometry, bed mm).
        """
        tp = self.tp
        sl = tp.layer_slice(i)
        p0, p1 = tp.start[sl].copy(), tp.end[sl].copy()
        w = tp.width[sl].astype(np.float64)
        scale = np.ones(len(p0))
        fx = ~part_mask(tp.feature[sl])  # skirt, brim, purge lines, wipe tower: not attached to the part
        removed = {}
        for k, rf in enumerate(self.failures):
            if rf.type in ("infill_defect", "thin_wall") and rf.failure.active(i):
                assert rf.select is not None  # resolve() selects segments for these types
                sel = rf.select[sl]
                ti, to = _clip_disc(p0, p1, rf.center, rf.failure.size_mm / 2)
                hit = sel & (to > ti) & (scale > 0.99)
                if not hit.any():
                    removed[k] = (np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
                    continue
                d = p1[hit] - p0[hit]
                a0, a1 = p0[hit] + ti[hit, None] * d, p0[hit] + to[hit, None] * d
                removed[k] = (a0, a1, w[hit])
                keep = ~hit
                parts = [(p0[keep], p1[keep], w[keep], scale[keep], fx[keep])]
                pre, post = ti[hit] > 1e-9, to[hit] < 1 - 1e-9
                wh, sh, fh = w[hit], scale[hit], fx[hit]
                parts.append((p0[hit][pre], a0[pre], wh[pre], sh[pre], fh[pre]))
                parts.append((a1[post], p1[hit][post], wh[post], sh[post], fh[post]))
                if rf.failure.mode == "under":
                    parts.append((a0, a1, wh, np.full(len(a0), 0.3), fh))
                p0, p1, w, scale, fx = (np.concatenate(x) for x in zip(*parts, strict=True))
        for rf in self.failures:
            if rf.type == "layer_shift" and i >= rf.failure.onset:
                p0, p1 = p0 + rf.offset, p1 + rf.offset
        return p0, p1, w, scale, removed, fx

    def extruded(self, i: int) -> bool:
        """False when a ``nothing_extruded`` failure is active on layer ``i`` (the nozzle prints in the air)."""
        return not any(rf.type == "nothing_extruded" and rf.failure.active(i) for rf in self.failures)

    def _deposit(self, i: int) -> None:
        for k, rf in enumerate(self.failures):
            if rf.type == "layer_shift" and rf.failure.onset == i:
                self.before_shift[k] = self.h.copy()
        if not self.extruded(i):
            return
        st = self.settings
        lay = self.tp.layers[i]
        lh = lay.height if lay.height > 0 else 0.2
        p0, p1, w, scale, _, fx = self.layer_segments(i)
        n = len(p0)
        if n == 0:
            return
        rng = np.random.default_rng([self.seed, 1, i])
        jit = rng.normal(0, st.position_jitter_mm, (n, 2))
        rows = np.empty((n, 10))
        rows[:, 0:2] = p0 + jit
        rows[:, 2:4] = p1 + jit
        rows[:, 4] = w / 2 * scale * np.clip(1 + rng.normal(0, st.width_jitter, n), 0.6, 1.4)
        rows[:, 5] = lay.z - lh / 2 + rng.normal(0, st.z_jitter_mm, n) - (1 - scale) * lh * 0.4
        rows[:, 6] = 0.0
        rows[:, 7] = lh / 2 * np.where(scale < 1, 0.5, 1.0)
        rows[:, 8] = st.extrusion_noise * rng.uniform(0.3, 1.0, n)
        rows[:, 9] = rng.uniform(0, 2 * np.pi, n)
        mats = np.full(n, fl.MAT_PART, np.uint8)
        for rf in self.failures:  # one object of a plate comes off: the others stay on the bed with the skirt
            if rf.type == "detachment" and rf.failure.within_mm is not None:
                fx = fx | ~fl.in_box(p0, p1, rf.failure.within_mm)
        part = ~fx
        # a plate's other objects (within_mm) print over air as the part does (one that starts on a higher
        # layer): the gaps are those of the whole plate's height map, as in the clean print, else the photos
        # differ from the clean print's before the onset
        both = self.has_fixed or bool(fx.any())
        before = np.maximum(self.h, self.hf) if both else self.h.copy()
        stamp_capsules(self.h, self.mat, self.h, rows[part], mats[part], *self.gp)
        if fx.any():
            self.has_fixed = True
            stamp_capsules(self.hf, self.matf, self.hf, rows[fx], mats[fx], *self.gp)
        self._record_gaps(before, np.maximum(self.h, self.hf) if both else self.h, lay.z - lh, lh)

    def _record_gaps(self, before: np.ndarray, after: np.ndarray, base: float, lh: float) -> None:
        """Cells where the new layer (bottom ``base`` mm) was printed over more than 2.5 layers of air.

        ``before``, ``after``: the height map (grid shape, mm) before and after the layer was stamped.
        """
        air = (after > before) & (before < base - _GAP_LAYERS * lh)
        # one gap per cell: the tallest (a window is not lost to a pinhole of the lintel above it)
        air &= base - before > self.gap[..., 1] - self.gap[..., 0]
        if air.any():
            self.gap[air, 0] = before[air]
            self.gap[air, 1] = base

    def advance(self, index: int) -> None:
        """Deposit layers up to ``index`` (rebuilding when going backwards)."""
        if index < self.next_layer - 1:
            self._reset()
        while self.next_layer <= index:
            self._deposit(self.next_layer)
            self.next_layer += 1

    # ----------------------------------------------------------------- frame
    def _detach(self, rf, h, mat, gap):
        s, ux0, vy0 = self.gp
        G = np.array([[s, 0, ux0], [0, -s, vy0], [0, 0, 1]])
        M = G @ _affine_mm(rf) @ np.linalg.inv(G)
        hs = cv2.warpAffine(h, M[:2], h.shape[::-1], flags=cv2.INTER_LINEAR)
        ms = cv2.warpAffine(mat, M[:2], h.shape[::-1], flags=cv2.INTER_NEAREST)
        xy = self.grid.to_mm(np.stack(np.meshgrid(np.arange(h.shape[1]), np.arange(h.shape[0])), -1))
        nrm = rf.offset / max(np.linalg.norm(rf.offset), 1e-9)
        lift = rf.tilt * np.maximum(((xy - rf.center) @ nrm) + _TILT_ARM_MM, 0).astype(np.float32)
        hs = np.where(hs > 0, hs + lift, 0).astype(np.float32)
        gs = cv2.warpAffine(gap, M[:2], h.shape[::-1], flags=cv2.INTER_NEAREST)
        gs = np.where((gs[..., 1:] > 0) & (hs[..., None] > 0), gs + lift[..., None], 0).astype(np.float32)
        return hs, ms, gs

    def _rest_height(self, h: np.ndarray, rows: np.ndarray) -> float:
        """Highest surface point under the capsules' bounding box, mm."""
        r = rows[:, 4].max()
        lo = rows[:, [0, 1]].min(0).clip(None, rows[:, [2, 3]].min(0)) - r
        hi = rows[:, [0, 1]].max(0).clip(rows[:, [2, 3]].max(0)) + r
        (u0, v1), (u1, v0) = np.round(self.grid.to_px(np.array([lo, hi]))).astype(int)
        H, W = h.shape
        win = h[max(v0, 0) : min(v1 + 1, H), max(u0, 0) : min(u1 + 1, W)]
        return float(win.max()) if win.size else 0.0

    def _refilled(self, h: np.ndarray, rf, index: int) -> np.ndarray:
        """``h`` with the beads a patch failure removed on its layers up to ``index`` printed (the plan)."""
        k = self.failures.index(rf)
        plan = h.copy()
        for j in range(rf.failure.onset, index + 1):
            a0, a1, w = self.layer_segments(j)[4].get(k, (np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)))
            if not len(a0) or not self.extruded(j):
                continue
            lay = self.tp.layers[j]
            lh = lay.height if lay.height > 0 else 0.2
            rows = np.zeros((len(a0), 10))
            rows[:, 0:2], rows[:, 2:4], rows[:, 4] = a0, a1, w / 2
            rows[:, 5], rows[:, 7] = lay.z - lh / 2, lh / 2
            stamp_capsules(plan, np.zeros(plan.shape, np.uint8), plan, rows, np.full(len(rows), fl.MAT_PART, np.uint8),
                           *self.gp)
        return plan

    def bed_photo(self) -> np.ndarray:
        """The empty bed as the same camera sees it before the print (no part, no failure).

        What ``layerwatch calibrate --markers`` keeps: the same camera, pose,
        lights and sensor model, with its own noise and exposure draw.

        Returns
        -------
        ndarray, uint8, shape (h, w, 3)
            BGR photo.
        """
        flat = np.zeros(self.grid.shape, np.float32)
        photo, _ = self.cam.shoot(flat, np.zeros(self.grid.shape, np.uint8), self.tp.n_layers + 1000, 0.2)
        return photo

    def frame(self, index: int) -> SimFrame:
        """Simulate the photo taken after layer ``index`` (0-based)."""
        if not 0 <= index < self.tp.n_layers:
            raise ConfigError(f"layer {index} does not exist (0..{self.tp.n_layers - 1}).")
        t0 = time.perf_counter()
        self.advance(index)
        tp, tv = self.tp, self.topview
        lay = tp.layers[index]
        h, mat, gap = self.h.copy(), self.mat.copy(), self.gap
        lh = lay.height if lay.height > 0 else 0.2
        sight = tr.Sight(self.C, tv, self.grid, lay.z)
        tol = tr.DEPTH_LAYERS * lh
        active = [rf for rf in self.failures if rf.failure.active(index)]
        plan = plan_gap = moved = None
        for rf in active:
            if rf.type == "detachment":
                plan, plan_gap = h.copy(), gap
                h, mat, gap = self._detach(rf, h, mat, gap)
                moved = h > 0
        if self.has_fixed:  # the skirt stays on the bed whatever the part does
            top = self.hf > h
            h[top], mat[top] = self.hf[top], self.matf[top]
            if moved is not None and plan is not None:
                moved &= ~top
                plan = np.maximum(plan, self.hf)
        raised = []  # (type, scene before the object) of foreign bodies and strands
        for rf in active:
            if rf.type in ("foreign_body", "spaghetti"):
                # resolve() builds the capsules and their materials for these types
                assert rf.capsules is not None and rf.capsule_mat is not None
                rows = rf.capsules.copy()
                if rf.type == "foreign_body":  # rests on the highest point under it
                    rows[:, 5] = self._rest_height(h, rows)
                else:
                    rows = rows[: rf.per_layer * (index - rf.failure.onset + 3)]
                before = h.copy()
                stamp_capsules(h, mat, before, rows, rf.capsule_mat[: len(rows)], *self.gp)
                raised.append(before)
        # the truth is what the camera sees of the failures in the final scene (simulate/truth.py)
        truth = np.zeros(tv.shape, bool)  # patches and objects: closed into their region below
        moved_truth = np.zeros(tv.shape, bool)  # already regions
        for rf in active:
            f = rf.failure
            if f.type == "detachment":
                assert moved is not None and plan is not None
                moved_truth |= tr.detachment(sight, h, gap, moved, plan, plan_gap, tol)
            elif f.type == "layer_shift":
                z_below = tp.layers[f.onset - 1].z if f.onset > 0 else 0.0
                below = self.before_shift[self.failures.index(rf)]
                if self.has_fixed:
                    below = np.maximum(below, self.hf)
                moved_truth |= tr.layer_shift(sight, h, gap, below, z_below, rf.offset, tol)
            elif f.type in ("infill_defect", "thin_wall"):
                truth |= tr.patch(sight, h, gap, self._refilled(h, rf, index), tol)
            elif f.type == "nothing_extruded":
                sl = tp.layer_slice(index)
                truth |= tr.nothing_extruded(solid_area(tp.start[sl], tp.end[sl], tp.width[sl] / 2.0, tv))
        for before in raised:
            truth |= tr.raised_object(sight, h, gap, before)
        # a patch's beads closed into its region; not the moved part's, which the closing would join
        # across the part where it is where it should be
        area = (_close(truth, tv, 3.0) | moved_truth) if active else None
        truth |= moved_truth
        photo, info = self.cam.shoot(h, mat, index, lay.height, gap)
        meta = {
            "layer": index,
            "z": lay.z,
            "failures": [rf.type for rf in active],
            "failed": bool(truth.any()),
            **info,
            "seconds": time.perf_counter() - t0,
        }
        return SimFrame(photo, truth if active else None, meta, area)

def _close(mask: np.ndarray, tv: TopView, mm: float) -> np.ndarray:
    k = max(int(round(mm * tv.px_per_mm)) | 1, 3)
    m = cv2.copyMakeBorder(mask.astype(np.uint8), k, k, k, k, cv2.BORDER_CONSTANT, value=0)
    m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    return m[k:-k, k:-k].astype(bool) | mask


def _affine_mm(rf) -> np.ndarray:
    """3x3 bed-mm affine of a detachment: rotate about the centre, then translate."""
    c, a = rf.center, rf.angle
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    M = np.eye(3)
    M[:2, :2] = R
    M[:2, 2] = c - R @ c + rf.offset
    return M


def _apply_affine(rf, p: np.ndarray) -> np.ndarray:
    M = _affine_mm(rf)
    return p @ M[:2, :2].T + M[:2, 2]


def simulate_print(
    toolpath: Toolpath,
    camera: CameraModel,
    topview: TopView,
    failures: Sequence[fl.Failure] = (),
    seed: int = 0,
    layers: Iterable[int] | None = None,
    settings: SimSettings | None = None,
) -> Iterator[SimFrame]:
    """Simulate the photos of a print, layer after layer (incremental height field).

    Parameters
    ----------
    toolpath, camera, topview
        The print, a posed camera (e.g. :func:`~layerwatch.simulate.scene.default_camera`)
        and the top view of the truth masks.
    failures : sequence of Failure
    seed : int
    layers : iterable of int, optional
        Layer indices to photograph (ascending is fastest); default all.
    settings : SimSettings, optional

    Yields
    ------
    SimFrame
    """
    sim = PrintSimulator(toolpath, camera, topview, failures, seed, settings)
    for i in range(toolpath.n_layers) if layers is None else layers:
        yield sim.frame(int(i))


def simulate_layer(
    toolpath: Toolpath,
    index: int,
    camera: CameraModel,
    topview: TopView,
    failures: Sequence[fl.Failure] = (),
    seed: int = 0,
    settings: SimSettings | None = None,
) -> SimFrame:
    """Simulate the photo taken after layer ``index``; same result as in :func:`simulate_print`."""
    return PrintSimulator(toolpath, camera, topview, failures, seed, settings).frame(index)
