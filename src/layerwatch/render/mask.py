"""Footprint masks: where material should be in a layer (S_P of the paper).

Two independent sources:

* :func:`gcode_mask` — the union of the layer's bead capsules (same kernel
  as the fast renderer, pixel centre inside a capsule);
* :func:`stl_mask` — the model's cross-section at height ``z`` (manifold3d
  slice of the mesh), rasterised by an even-odd scanline fill so holes stay empty (checked
  against ``cv2.fillPoly`` in the tests).

References
----------
Petsiuk & Pearce (2022), eq. (5): the anomaly ratio counts only blocks of
the printed area S_P.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
from numba import njit

from layerwatch.errors import RenderError
from layerwatch.gcode.toolpath import Toolpath, feature_code
from layerwatch.geometry.topview import TopView
from layerwatch.render.fast import _check_index, segment_pixels
from layerwatch.render.raster import raster_capsules

__all__ = ["closed_loops", "gcode_mask", "stl_mask", "load_mesh", "slice_polygons", "fill_polygons"]

log = logging.getLogger(__name__)

def closed_loops(
    start: np.ndarray, end: np.ndarray, tol: float = 1e-3, close_mm: float = 1.0
) -> list[np.ndarray]:
    """Closed chains of consecutive segments (perimeter loops), as polygons.

    Parameters
    ----------
    start, end : ndarray, shape (S, 2)
        Segments of one layer in print order, mm.
    tol : float
        Largest gap between consecutive segments of one chain, mm.
    close_mm : float
        Largest gap between a chain's end and its start (slicers leave a
        seam gap of a fraction of the bead width), mm.

    Returns
    -------
    list of ndarray, shape (K, 2)
        Vertices of every chain of >= 3 segments whose end comes back to its start.
    """
    n = start.shape[0]
    if n == 0:
        return []
    breaks = np.flatnonzero(np.hypot(*(start[1:] - end[:-1]).T) > tol) + 1
    bounds = np.concatenate([[0], breaks, [n]])
    loops = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b - a >= 3 and np.hypot(*(end[b - 1] - start[a])) <= close_mm:
            loops.append(start[a:b])
    return loops


def gcode_mask(toolpath: Toolpath, index: int, topview: TopView, *, solid: bool = False) -> np.ndarray:
    """Footprint of layer ``index``: union of its bead capsules.

    With ``solid=True`` the inside of the layer's closed external-perimeter
    loops is added (even-odd rule: one external perimeter per contour or
    hole, so holes stay empty), so sparse-infill layers give the part's
    cross-section. Without feature tags (all segments "unknown") every
    closed loop is used.

    Parameters
    ----------
    toolpath : Toolpath
    index : int
        Layer index (negative counts from the end).
    topview : TopView

    Returns
    -------
    ndarray, shape (H, W), bool
        True where a pixel centre lies within half a bead width of a segment
        of the layer (plus the filled loops with ``solid``). Empty layers
        give an all-False mask.
    """
    index = _check_index(toolpath, index)
    shape = topview.shape
    mask = np.zeros(shape, bool)
    sl = toolpath.layer_slice(index)
    if toolpath.layers[index].n_segments == 0:
        return mask
    p0, p1, r = segment_pixels(toolpath, sl, topview)
    dummy = np.zeros(p0.shape[0], np.float64)
    height = np.zeros(shape, np.float32)
    clipped = raster_capsules(height, mask, p0, p1, r, dummy, dummy, False, True)
    if clipped:
        log.warning("layer %d: %d segments clipped by the observed square", index, clipped)
    if solid:
        feat = toolpath.feature[sl]
        sel = feat == feature_code("external_perimeter")
        if not sel.any():
            sel = feat == feature_code("unknown")
        if sel.any():
            wmax = float(np.max(toolpath.width[sl][sel]))
            loops = closed_loops(toolpath.start[sl][sel], toolpath.end[sl][sel], close_mm=2.0 * wmax)
            mask |= fill_polygons(loops, topview)
    return mask


def load_mesh(mesh_or_path):
    """Load an STL/3MF/OBJ (or take a ``trimesh.Trimesh``) and make it watertight.

    Returns
    -------
    trimesh.Trimesh
        A watertight mesh (holes filled, normals fixed when needed).

    Raises
    ------
    RenderError
        Unreadable file, empty mesh, or a mesh that cannot be repaired.
    """
    import trimesh  # (here: 0.4 s to import, and the G-code masks above do without it)

    if isinstance(mesh_or_path, trimesh.Trimesh):
        mesh = mesh_or_path.copy()
        name = "mesh"
    else:
        p = Path(mesh_or_path)
        name = str(p)
        if not p.is_file():
            raise RenderError(f"mesh file {p} not found; give the path of the part's STL/3MF.")
        try:
            loaded = trimesh.load(p, force="mesh")
        except Exception as exc:  # trimesh raises many types on bad files
            raise RenderError(f"{p}: cannot read mesh ({exc}); export it again as binary STL.") from None
        mesh = loaded
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise RenderError(f"{name}: contains no triangles; export the part as STL/3MF.")
    if not mesh.is_watertight:
        mesh.merge_vertices()
        trimesh.repair.fix_normals(mesh)
        trimesh.repair.fill_holes(mesh)
        if not mesh.is_watertight:
            raise RenderError(
                f"{name}: mesh is not watertight and could not be repaired; "
                "repair it (e.g. PrusaSlicer 'Fix model') and try again."
            )
        log.warning("%s: mesh was not watertight; holes were filled", name)
    return mesh


def slice_polygons(mesh, z: float) -> list[np.ndarray]:
    """Cross-section of a watertight mesh at height ``z`` as closed polygons.

    Returns
    -------
    list of ndarray, shape (K, 2), float64
        Outer boundaries and holes in bed mm (manifold3d winding: outer
        counter-clockwise, holes clockwise).
    """
    import manifold3d

    man = manifold3d.Manifold(
        manifold3d.Mesh(
            vert_properties=np.asarray(mesh.vertices, np.float32),
            tri_verts=np.asarray(mesh.faces, np.uint32),
        )
    )
    if man.status() != manifold3d.Error.NoError:
        raise RenderError(f"mesh is not a valid solid ({man.status()}); repair the STL and try again.")
    return [np.asarray(p, np.float64) for p in man.slice(float(z)).to_polygons()]


@njit(cache=True)
def _fill_scanline(mask, xs0, ys0, xs1, ys1, nonzero):
    """Scanline polygon fill at pixel centres (exact area on average).

    ``nonzero`` False: even-odd rule; True: nonzero winding rule.
    """
    H, W = mask.shape
    n = xs0.shape[0]
    cross = np.empty(n, np.float64)
    wind = np.empty(n, np.int64)
    for v in range(H):
        y = float(v)
        k = 0
        for i in range(n):
            a, b = ys0[i], ys1[i]
            if (a <= y < b) or (b <= y < a):
                t = (y - a) / (b - a)
                cross[k] = xs0[i] + t * (xs1[i] - xs0[i])
                wind[k] = 1 if b > a else -1
                k += 1
        if k < 2:
            continue
        order = np.argsort(cross[:k])
        acc = 0
        for jj in range(k - 1):
            j = order[jj]
            acc = acc + wind[j] if nonzero else 1 - acc
            if acc != 0:
                u0 = max(int(math.ceil(cross[j])), 0)
                u1 = min(int(math.ceil(cross[order[jj + 1]])) - 1, W - 1)
                for u in range(u0, u1 + 1):
                    mask[v, u] = True


def fill_polygons(polygons: list[np.ndarray], topview: TopView, *, nonzero: bool = False) -> np.ndarray:
    """Rasterise closed polygons, even-odd (default) or nonzero winding rule.

    A pixel is set when its centre is inside (left-closed, right-open spans),
    so the pixel count times ``1 / px_per_mm**2`` estimates the area without
    the outline bias of ``cv2.fillPoly``.

    Parameters
    ----------
    polygons : list of ndarray, shape (K, 2)
        Polygons in bed mm (orientation matters only for ``nonzero``).
    nonzero : bool
        Nonzero winding rule (counter-clockwise adds, clockwise removes).
    topview : TopView

    Returns
    -------
    ndarray, shape (H, W), bool
    """
    mask = np.zeros(topview.shape, bool)
    polys = [topview.to_px(p) for p in polygons if len(p) >= 3]
    if polys:
        a = np.concatenate(polys)
        b = np.concatenate([np.roll(p, -1, axis=0) for p in polys])
        _fill_scanline(mask, a[:, 0].copy(), a[:, 1].copy(), b[:, 0].copy(), b[:, 1].copy(), nonzero)
    return mask


def stl_mask(mesh_or_path, z: float, topview: TopView, *, offset_mm=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Footprint of the model at height ``z``: its slice, rasterised.

    Parameters
    ----------
    mesh_or_path : str or Path or trimesh.Trimesh
        The part (STL, 3MF, OBJ). Non-watertight meshes are repaired or refused.
    z : float
        Slicing height in bed mm (for a layer, use its middle: ``z - h / 2``).
    topview : TopView
    offset_mm : tuple of float
        Translation ``(dx, dy, dz)`` from mesh coordinates to bed mm (where the
        slicer placed the part).

    Returns
    -------
    ndarray, shape (H, W), bool

    Raises
    ------
    RenderError
        Missing/unreadable file or a mesh that cannot be made watertight.
    """
    mesh = load_mesh(mesh_or_path)
    off = np.asarray(offset_mm, np.float64)
    polys = slice_polygons(mesh, float(z) - off[2])
    return fill_polygons([p + off[:2] for p in polys], topview)
