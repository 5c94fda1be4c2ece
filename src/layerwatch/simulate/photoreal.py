"""Photoreal simulated photos: the simulator's scene rendered by Blender Cycles through the calibrated camera.

The raster photographer (:class:`~layerwatch.simulate.photo.Photographer`)
ray-casts the simulator's height field with a Blinn-Phong model of its own.
:class:`BlenderPhotographer` hands the same scene to a path tracer instead
(``[simulate] renderer = "blender"``, ``layerwatch simulate --photoreal``):
soft shadows of a lamp with a size, inter-reflections between the part and
the bed, a microfacet (GGX) specular lobe, light that grazes walls as it does
on a printer. Everything else of a simulated frame is shared: the geometry and
its failures (the height field and per-cell materials of
:class:`~layerwatch.simulate.camera_sim.PrintSimulator`), the frame's light
position and strengths (:meth:`~layerwatch.simulate.photo.Photographer.light`),
the truth masks, and the sensor (exposure and white-balance drift, vignetting,
blur, shot and read noise, gamma: :meth:`~layerwatch.simulate.photo.Photographer.develop`
develops Cycles' linear radiance as it develops the raster's).

The scene (:mod:`layerwatch.simulate.photoreal_scene`, run inside Blender):

* the printed cells as a height-field mesh (one vertex a cell of the
  simulator's grid, bed mm, on the box of the printed cells), each vertex with
  its material's albedo, specular weight and roughness; where a bridge, an
  overhang or a ledge stands over the bed, the ground under it is the bed's
  (:func:`ground_materials`: a cell's material is its top's);
* the bed as a plane textured with the bed's albedo (sheet texture, white dot
  markers: the same function the raster draws it with), a dark floor beyond;
* a spot of ``radius 5 mm`` where the frame's spot is, an overhead sun for the
  fill, a uniform world for the ambient, their strengths set so that a white
  Lambertian sheet facing each light reads what the raster model gives it;
* a pinhole camera with the intrinsics of ``K`` at the camera's centre; the
  lens distortion is applied to the render afterwards (:meth:`BlenderPhotographer.radiance`),
  so markers and part land on the pixels the calibration predicts.

Limits: the cells are meshed at the simulator's grid (0.125 mm), one vertex a
cell, so a wall is as sharp as the raster's and bead layer lines on walls are only
the grid's; the air under a bridge, an overhang or a window's lintel (the
simulator's one ``gap`` a cell) is kept open where a camera could see into it, sealed
pockets (sparse infill under a top skin) are solid (:func:`scene_meshes`). Cycles takes
seconds per frame (about 10-40 s at 1280 x 720 and 32 samples on two cores):
the mode is for photoreal checks and benchmarks, not the routine evaluation.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import tempfile
import weakref
from pathlib import Path

import cv2
import numpy as np

from layerwatch.analysis.block_masks import touching
from layerwatch.errors import RenderError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.render.blender import find_blender
from layerwatch.simulate.photo import Photographer, fold_ledges
from layerwatch.simulate.settings import SimSettings
from layerwatch.simulate.shade import bed_albedo_at

__all__ = ["BlenderPhotographer", "blender_camera", "ground_materials", "open_air", "scene_meshes", "SCENE_SCRIPT"]

SCENE_SCRIPT = Path(__file__).with_name("photoreal_scene.py")

#: Blender's sensor width for the pinhole (any value: the focal length follows it), mm
SENSOR_WIDTH_MM = 36.0
#: radius of the lamp (soft shadows), mm
LAMP_RADIUS_MM = 5.0
#: cells of bare bed kept around the printed cells in the height-field mesh
FIELD_BORDER_CELLS = 2
#: the shortest rim through which a camera sees into air under printed material (a window, an overhang), mm;
#: shorter ones are pinholes the grid left in a skin (:func:`open_air`)
OPENING_MM = 1.0
#: bed texture resolution, px/mm, at most (and at most 4096 px a side)
BED_TEXTURE_PX_PER_MM = 8.0


def blender_camera(camera: CameraModel) -> dict:
    """The Blender pinhole camera that sees the bed as ``camera`` does without its lens distortion.

    OpenCV's camera looks along +z with image y down, pixel centres at whole
    coordinates; Blender's looks along -z with y up, a pixel's centre half a
    pixel into it. The principal point becomes the lens shift, in units of the
    image width (``sensor_fit = "HORIZONTAL"``).

    Parameters
    ----------
    camera : CameraModel
        Posed camera; ``fx`` and ``fy`` equal within 0.1 % (square pixels).

    Returns
    -------
    dict
        ``camera_to_bed`` (4 x 4 rows, mm), ``lens_mm``, ``sensor_width_mm``, ``shift`` ``(x, y)``,
        ``resolution`` ``(width, height)`` px.

    Raises
    ------
    RenderError
        The camera has non-square pixels.
    """
    K = np.asarray(camera.K, float)
    w, h = (int(v) for v in camera.image_size)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if abs(fx - fy) > 1e-3 * fx:
        raise RenderError(f"the photoreal renderer needs square pixels; the camera has fx {fx:.1f} and fy {fy:.1f} px.")
    R = np.asarray(camera.R, float)  # rows: the camera's axes in the bed frame
    m = np.eye(4)
    m[:3, :3] = np.stack([R[0], -R[1], -R[2]], axis=1)
    m[:3, 3] = np.asarray(camera.center_mm, float)
    return {
        "camera_to_bed": m.tolist(),
        "lens_mm": float(fx * SENSOR_WIDTH_MM / w),
        "sensor_width_mm": SENSOR_WIDTH_MM,
        "shift": [float((w / 2 - cx - 0.5) / w), float((cy + 0.5 - h / 2) / w)],
        "resolution": [w, h],
    }


def _spot(light: np.ndarray) -> dict:
    """The frame's spot (:meth:`Photographer.light`) as a Blender spot: pose, cone, power in W."""
    pos, axis = np.asarray(light[:3], float), np.asarray(light[3:6], float)
    z = -axis / np.linalg.norm(axis)  # a Blender spot shines along its -z
    x = np.cross([0.0, 0.0, 1.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z], axis=1)
    m[:3, 3] = pos
    inner, outer = math.degrees(math.acos(light[6])), math.degrees(math.acos(light[7]))
    # Cycles: a point or spot light of power P gives a white Lambertian sheet facing it at distance d
    # the radiance P / (4 pi^2 d^2); the raster gives it I (dref / d)^2
    return {"matrix": m.tolist(), "outer_deg": outer, "blend": (outer - inner) / outer,
            "radius_mm": LAMP_RADIUS_MM, "power_w": float(4 * math.pi**2 * light[8] * light[11] ** 2)}


class BlenderPhotographer(Photographer):
    """The simulator's photographer with Blender Cycles for the scene's radiance (see module notes).

    Parameters
    ----------
    camera, topview, grid, settings, seed
        As :class:`~layerwatch.simulate.photo.Photographer`; ``settings.blender_samples``,
        ``blender_threads`` and ``blender_timeout_s`` set the render.
    executable : str, optional
        Blender executable (default ``$LAYERWATCH_BLENDER`` or ``blender`` on PATH).

    Raises
    ------
    MissingBlenderError
        ``blender`` is not installed (one line naming how to install it).
    RenderError
        The camera has non-square pixels.
    """

    def __init__(self, camera: CameraModel, topview: TopView, grid: TopView, settings: SimSettings, seed: int,
                 executable: str | None = None) -> None:
        super().__init__(camera, topview, grid, settings, seed)
        self.executable = find_blender(executable)
        self.view = blender_camera(camera)
        #: scratch folder of the renders (bed texture, each frame's job), removed with the photographer
        self.workdir = Path(tempfile.mkdtemp(prefix="layerwatch-photoreal-"))
        weakref.finalize(self, shutil.rmtree, self.workdir, True)
        self._renders = 0
        self._bed_texture = self._write_bed_texture()
        self._map_x, self._map_y = self._distortion_maps()

    # ------------------------------------------------------------------ set-up
    def _write_bed_texture(self) -> Path:
        """The bed's albedo on its square as a linear 16-bit PNG (row 0 at the bed's far edge, +y)."""
        x0, y0, x1, y1 = (float(v) for v in self.bed)
        ppm = min(BED_TEXTURE_PX_PER_MM, 4096.0 / max(x1 - x0, y1 - y0))
        nx, ny = max(2, int(round((x1 - x0) * ppm))), max(2, int(round((y1 - y0) * ppm)))
        xs = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
        ys = y1 - (np.arange(ny) + 0.5) * (y1 - y0) / ny
        gx, gy = np.meshgrid(xs, ys)
        rgb = self._bed_albedo(gx.ravel(), gy.ravel()).reshape(ny, nx, 3)
        path = self.workdir / "bed.png"
        cv2.imwrite(str(path), np.round(np.clip(rgb[..., ::-1], 0, 1) * 65535).astype(np.uint16))
        return path

    def _surface(self, m: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Albedo RGB (n, m, 3) and Cycles (specular, roughness) (n, m, 2) of cells of material ``m`` at bed
        points ``xy`` (n, m, 2) mm: the material's, the bed's texture where ``m`` is 0 (bare bed)."""
        albedo = np.empty((*m.shape, 3), np.float32)
        albedo[:] = self.albedo[m]
        bed = m == 0
        if bed.any():
            albedo[bed] = self._bed_albedo(xy[bed][:, 0], xy[bed][:, 1])
        spec = np.stack([np.minimum(2 * self.spec[m, 0], 1.0), _roughness(self.spec[m, 1])], axis=-1)
        return albedo, spec

    def _bed_albedo(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Albedo RGB of the bare bed at bed points (mm), float32 (n, 3)."""
        st = self.settings
        return bed_albedo_at(np.ascontiguousarray(x, np.float64), np.ascontiguousarray(y, np.float64), self.bed,
                             np.asarray(st.bed_rgb, float), np.asarray(st.background_rgb, float), self.markers,
                             st.marker_diameter_mm / 2, self.seed)

    def _distortion_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Per photo pixel, where its ray meets the undistorted (pinhole) render, px (``cv2.remap`` maps)."""
        d = self.dirs @ np.asarray(self.camera.R, np.float32).T  # camera-frame ray of every photo pixel
        K = np.asarray(self.camera.K, np.float64)
        z = np.maximum(d[..., 2], 1e-6)
        mx = (K[0, 0] * d[..., 0] / z + K[0, 2]).astype(np.float32)
        my = (K[1, 1] * d[..., 1] / z + K[1, 2]).astype(np.float32)
        return mx, my

    # ------------------------------------------------------------------ a frame
    def radiance(self, h: np.ndarray, mat: np.ndarray, layer_h: float, gap: np.ndarray | None,
                 light: np.ndarray) -> np.ndarray:
        """Linear RGB radiance from Cycles, float32 (h, w, 3), lens distortion applied.

        Raises
        ------
        RenderError
            Blender failed, crashed or ran past ``settings.blender_timeout_s``.
        """
        st = self.settings
        self._renders += 1
        frame = self.workdir / f"frame{self._renders}"
        frame.mkdir()
        job: dict = {**self.view, "output": str(frame / "out.png"), "bed_texture": str(self._bed_texture),
                     "bed_box_mm": [float(v) for v in self.bed], "background_rgb": list(st.background_rgb),
                     "bed_specular": float(min(2 * self.spec[0, 0], 1.0)),
                     "bed_roughness": float(_roughness(self.spec[0, 1])),
                     "spot": _spot(light), "fill_strength": float(math.pi * light[10]), "ambient": float(light[9]),
                     "samples": int(st.blender_samples), "threads": int(st.blender_threads),
                     "seed": int((self.seed * 1_000_003 + self._renders) % 2**31)}
        job.update(self._field(h, mat, gap, frame))
        (frame / "job.json").write_text(json.dumps(job))
        cmd = [self.executable, "-b", "--factory-startup", "-noaudio", "--python-exit-code", "3",
               "-P", str(SCENE_SCRIPT), "--", str(frame / "job.json")]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=st.blender_timeout_s)
        except subprocess.TimeoutExpired:
            raise RenderError(f"Blender did not finish a photo within {st.blender_timeout_s:.0f} s; raise "
                              "[simulate] blender_timeout_s or lower blender_samples.") from None
        except OSError as exc:
            raise RenderError(f"cannot start Blender ({exc}); check `{self.executable}` runs.") from None
        out = frame / "out.png"
        img = cv2.imread(str(out), cv2.IMREAD_UNCHANGED) if out.is_file() else None
        w, hh = self.camera.image_size
        if proc.returncode != 0 or img is None or img.shape[:2] != (hh, w) or img.dtype != np.uint16:
            tail = " | ".join((proc.stderr or proc.stdout or "").strip().splitlines()[-3:])
            raise RenderError(f"Blender failed on a photoreal photo (exit {proc.returncode}): {tail[:300]}; "
                              "check the Blender installation or use the raster renderer.")
        shutil.rmtree(frame)
        rad = img[..., 2::-1].astype(np.float32) / 65535.0  # BGR -> RGB, linear
        return cv2.remap(rad, self._map_x, self._map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def _field(self, h: np.ndarray, mat: np.ndarray, gap: np.ndarray | None, frame: Path) -> dict:
        """Write the printed scene's meshes for the job (see :func:`scene_meshes`); the job's ``meshes`` entry."""
        printed = h > 0
        if not printed.any():
            return {"meshes": []}
        rows, cols = np.flatnonzero(printed.any(1)), np.flatnonzero(printed.any(0))
        b = FIELD_BORDER_CELLS
        v0, v1 = max(rows[0] - b, 0), min(rows[-1] + b + 1, h.shape[0])
        u0, u1 = max(cols[0] - b, 0), min(cols[-1] + b + 1, h.shape[1])
        box = (slice(v0, v1), slice(u0, u1))
        vv, uu = np.mgrid[box]
        xy = self.grid.to_mm(np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)).reshape(*vv.shape, 2)
        m = mat[box]
        g = None if gap is None else gap[box]
        out = []
        for k, (verts, quads, at) in enumerate(scene_meshes(xy, fold_ledges(h)[box], g)):
            # the ground mesh is one vertex a cell (k = 0); where it lies on the bed it is the bed
            albedo, spec = self._surface(ground_materials(m, verts[:, 2].reshape(m.shape)) if k == 0 else m, xy)
            arrays = {"verts": verts.astype("<f4"), "quads": quads.astype("<i4"),
                      "albedo": np.column_stack([albedo.reshape(-1, 3)[at], np.ones(len(at))]).astype("<f4"),
                      "spec": spec.reshape(-1, 2)[at].astype("<f4")}
            entry = {}
            for name, arr in arrays.items():
                path = frame / f"mesh{k}_{name}.bin"
                path.write_bytes(np.ascontiguousarray(arr).tobytes())
                entry[name] = str(path)
            out.append(entry)
        return {"meshes": out}


def ground_materials(mat: np.ndarray, ground_z: np.ndarray) -> np.ndarray:
    """The material of each cell's vertex in the ground mesh (:func:`scene_meshes`): the bed's (0) where
    the mesh lies on the bed, the cell's own elsewhere.

    A cell's material (``mat``) is that of its top. Under a bridge, an overhang or a ledge the ground
    mesh is opened down to the bed (its air's ``lo`` is 0), so it takes the bed's albedo and gloss; under
    a window's lintel it is the sill, the part's material.

    Parameters
    ----------
    mat : ndarray, int, shape (n, m)
        Material index per cell (0: bare bed).
    ground_z : ndarray, float, shape (n, m)
        Height of the ground mesh's vertex of each cell, mm.

    Returns
    -------
    ndarray, shape (n, m)
        ``mat`` with 0 where ``ground_z`` is at the bed (0 or below).
    """
    return np.where(np.asarray(ground_z) <= 0.0, 0, mat).astype(mat.dtype)


def scene_meshes(xy: np.ndarray, h: np.ndarray, gap: np.ndarray | None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The simulator's cells as quad meshes: the ground and, where material was printed over air, a slab.

    A cell of the simulator is solid from the bed to ``h``, except its ``gap`` interval ``(lo, hi)``
    (the air under a bridge, an overhang, a window's lintel; ``hi = 0``: none). The ground mesh is
    the height field of ``lo`` on such cells and ``h`` elsewhere (so the air is open: a window shows
    what is behind it); the slab is the material from ``hi`` to ``h`` over the cells with a gap, a
    closed shell (top, underside facing down, walls at its border). One vertex a cell at the cell's
    centre; a quad joins four neighbouring cells (the slab's: four cells with a gap). Air sealed on
    every side (:func:`open_air`: the pockets of sparse infill under a top skin) is meshed solid: no
    camera sees it, and opened it left a groove one cell wide and millimetres deep beside every
    infill line, which Cycles drew as the infill's pattern on the top surface.

    Parameters
    ----------
    xy : ndarray, float, shape (n, m, 2)
        Bed mm of each cell's centre.
    h : ndarray, float32, shape (n, m)
        Height of each cell's top, mm.
    gap : ndarray, float32, shape (n, m, 2), or None

    Returns
    -------
    list of (verts, quads, cells)
        Per mesh: vertices (V, 3) mm, quads (Q, 4) vertex indices counter-clockwise seen from
        outside, and the flat cell index (V,) whose material each vertex takes.
    """
    n, m = h.shape
    idx = np.arange(n * m).reshape(n, m)
    lo, hi = (np.zeros((n, m)), np.zeros((n, m))) if gap is None else (gap[..., 0], gap[..., 1])
    cell_mm = float(np.hypot(*(xy[0, 1] - xy[0, 0]))) if m > 1 else 0.125
    air = open_air(h, hi, min_opening=int(np.ceil(OPENING_MM / max(cell_mm, 1e-3))))
    ground = np.where(air, lo, h).astype(np.float64)
    # counter-clockwise seen from +z: a cell, the one below it (y decreases with rows), then to the right
    a = idx[:-1, :-1].ravel()
    quads = np.stack([a, a + m, a + m + 1, a + 1], axis=1)
    out = [(np.column_stack([xy.reshape(-1, 2), ground.ravel()]), quads, idx.ravel())]
    if not air.any():
        return out
    inside = air[:-1, :-1] & air[1:, :-1] & air[1:, 1:] & air[:-1, 1:]
    if not inside.any():
        return out
    cells = np.flatnonzero(air)
    top_of = np.full(n * m, -1)
    top_of[cells] = np.arange(len(cells))
    k = len(cells)
    verts = np.concatenate([np.column_stack([xy.reshape(-1, 2)[cells], h.ravel()[cells]]),
                            np.column_stack([xy.reshape(-1, 2)[cells], hi.ravel()[cells]])])
    q = top_of[quads[inside.ravel()]]  # (Q, 4) top vertices
    faces = [q, q[:, ::-1] + k]  # the top; the underside, facing down
    # walls along the slab's border: a quad edge that no other slab quad shares
    edges = np.concatenate([q[:, [0, 1]], q[:, [1, 2]], q[:, [2, 3]], q[:, [3, 0]]])
    key = np.sort(edges, axis=1)
    _, inv, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    border = edges[count[inv.ravel()] == 1]
    faces.append(np.column_stack([border[:, 1], border[:, 0], border[:, 0] + k, border[:, 1] + k]))
    return out + [(verts, np.concatenate(faces), np.concatenate([cells, cells]))]


def open_air(h: np.ndarray, hi: np.ndarray, min_opening: int = 8, tol_mm: float = 0.05) -> np.ndarray:
    """The cells whose air under printed material a camera could see: their pocket is open to the side.

    A pocket is a 4-connected set of cells with air (``hi > 0``) after a 3 x 3 morphological opening
    (channels and slivers one or two cells wide, 0.25 mm at the simulator's grid, are the grid's
    rendering of beads that touch: they neither join pockets nor stay open). It is open when at
    least ``min_opening`` of its cells have a neighbour whose top lies below that cell's air
    (``h < hi - tol_mm``: the bed in front of a window, the space beside an overhang or under a
    bridge's end) or lie on the grid's border; else it is sealed (the sparse infill under a top skin,
    enclosed by the infill lines and the perimeters; a pinhole in the skin, where the jittered beads
    left a cell or two uncovered, does not open it) and only its slab's top can be seen.

    Parameters
    ----------
    h : ndarray, float, shape (n, m)
        Height of each cell's top, mm.
    hi : ndarray, float, shape (n, m)
        Top of each cell's air, mm (0: no air).
    min_opening : int
        Cells of a pocket's rim that must look out for it to be open (8: 1 mm at the simulator's grid).
    tol_mm : float
        A neighbour this far below the air's top still closes it, mm.

    Returns
    -------
    ndarray, bool, shape (n, m)
        Air cells of open pockets.
    """
    # pockets joined or opened only through channels one or two cells wide are the grid's quantisation of
    # beads that touch (a hairline between an infill line's capsules), not openings: they are left out
    air = cv2.morphologyEx((np.asarray(hi) > 0).view(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
    if not air.any():
        return air
    n, m = air.shape
    pad_h = np.pad(np.asarray(h, np.float64), 1, constant_values=-np.inf)  # beyond the grid: open
    pad_air = np.pad(air, 1, constant_values=False)
    seen = np.zeros_like(air)
    for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        nb_h = pad_h[1 + dv:n + 1 + dv, 1 + du:m + 1 + du]
        nb_air = pad_air[1 + dv:n + 1 + dv, 1 + du:m + 1 + du]
        seen |= air & ~nb_air & (nb_h < hi - tol_mm)  # a neighbour in the pocket's own air is no opening
    return touching(air, seen, connectivity=4, min_seeds=max(int(min_opening), 1))


def _roughness(shininess: np.ndarray | float) -> np.ndarray:
    """Microfacet roughness of a Blinn-Phong exponent (``sqrt(2 / (n + 2))``, Walter et al. 2007), 0.05-1."""
    return np.clip(np.sqrt(2.0 / (np.asarray(shininess, float) + 2.0)), 0.05, 1.0)
