"""A gap in a wall runs along the wall: unchanged perimeter pixels count only in a run along it.

Part of the "changed as predicted" channel (:mod:`layerwatch.analysis.layer_change`,
series mode). A thin-wall defect is a stretch of a perimeter that was not
printed: the surface below stays in place for the gap's whole length (the
simulator's gaps are 5-10 mm along the perimeter, a real under-extruded or
skipped stretch is as long as the nozzle ran dry). A printed perimeter laid on
its twin can look in place too, but only in short pieces: a bead's width and
placement wobble by a tenth of a millimetre along its length, so its
silhouette matches the previous photo in place here and there, in pieces of
about a millimetre and a half with changed wall between them (seen on the
example part's clean layers, e.g. the infill box's front wall of print 140
layer 16).

So on the G-code's perimeters (:func:`wall_top`, at their bead widths) the
per-pixel test of :func:`~layerwatch.analysis.layer_change.window_change` is
also read with a looser threshold (``wall_min_ncc``, ``wall_min_gain``: a
gap's pixels are often seen a fraction of a pixel off and correlate at 0.7-0.8
only), and such a perimeter pixel is unchanged too when its connected run of
such pixels (bridged over ``WALL_BRIDGE_PX``) is at least ``wall_run_mm`` long
on the layer's plane (:func:`wall_runs`: the run's
length: the extent of its pixels' bed coordinates along their principal axis). The
channel's own verdict stands everywhere: the runs only add (requiring the run of the
channel's own perimeter pixels too dropped print 140 layer 16's clean pieces, but also
short true detections: held-out seeds 40-45 thin-wall AUROC 0.854 -> 0.832). The silhouette rule
(:func:`~layerwatch.analysis.layer_change.drop_edge_slivers`) applies to the
candidates as to the channel's own verdict (with the footprint going on for
a whole band beyond the band instead, the window part's 1.8 mm walls gave
long runs of a silhouette that stayed in place: two new clean alarms on print
1101, layers 24 and 65).

A run must also lie across the camera's line of sight (:data:`MIN_RAY_ANGLE_DEG`
between the run's axis and the horizontal direction of the camera's rays
there; :func:`wall_runs` with ``ray``). A wall that runs along the line of
sight is seen along the parallax direction: the rise moves its texture along
itself, so its printed twin and the surface left in place look alike, and only
the wall's curvature makes them differ at all. There a printed wall passes the
looser test in long runs: the side extremes of Simplify3D 4.1.2's disc, where
its outer wall turns along the line of sight (``test_seen_past``'s clean layer
13 after 7: 108 px, 2.6 mm^2, added next to the channel's own 3.5 mm^2). On the
example part (seeds 10-11, tuning) 11 of the 16 runs >= 2.5 mm of clean photos
lay within 18 deg of the line of sight, 2 of the 67 runs over true gaps did
(16 and 18 deg). The channel's own verdict stands there as everywhere.

Pixels without a verdict (a black or missing previous photo, flat texture,
or a window that took a quarter of its texture from what the previous photo
saw past the part: :mod:`layerwatch.analysis.seen_past`, removed from
``change.judged`` before the runs) are never candidates: no run, no region.
Nor, for the looser test, is a pixel whose window took even
:data:`WALL_BLIND_SHARE` (5 %) of its previous texture from there: the far
wall rising over a skirt close behind it lands its silhouette where the
skirt's line was, and at NCC 0.7 a small share of that line is enough
(Simplify3D 4.1.2's clean layer 13, consecutive photos, prints 101, 103, 104:
runs of 13-18 mm along the far wall, 21-23 mm^2 where main has 3-8; at a
share of 0.1 338 of the 454 added pixels are out, at 0.05 435).
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.analysis.layer_change import (
    EDGE_DEPTH,
    LayerChangeSettings,
    WindowChange,
    drop_edge_slivers,
)
from layerwatch.gcode.toolpath import FEATURES, Toolpath
from layerwatch.geometry.topview import TopView

__all__ = ["MIN_RAY_ANGLE_DEG", "WALL_BLIND_SHARE", "WALL_BRIDGE_PX", "ray_angles", "run_axes", "run_lengths", "wall_runs", "wall_top", "wall_verdict"]

#: candidate pixels this close (working px, square neighbourhood) along a perimeter belong to one run
WALL_BRIDGE_PX = 1
#: a run whose axis lies closer than this (degrees) to the horizontal direction of the camera's rays is
#: not counted: along the line of sight a printed wall's twin looks like the wall in place (module notes)
MIN_RAY_ANGLE_DEG = 15.0
#: a perimeter pixel whose window took this share of its previous texture from what the previous photo
#: saw past the part (:func:`~layerwatch.analysis.seen_past.past_share`) is no candidate (module notes)
WALL_BLIND_SHARE = 0.05
_WALLS = tuple(FEATURES.index(n) for n in ("perimeter", "external_perimeter"))


def wall_top(toolpath: Toolpath, index: int, topview: TopView) -> np.ndarray:
    """The perimeters that layer ``index`` plans, drawn at their bead widths in the top view.

    Returns
    -------
    ndarray, bool, shape ``topview.shape``
    """
    sl = toolpath.layer_slice(index)
    use = np.isin(toolpath.feature[sl], _WALLS)
    out = np.zeros(topview.shape, np.uint8)
    if not use.any():
        return out.astype(bool)
    shift = 4  # cv2's sub-pixel coordinates: 1/16 px
    p0 = np.round(topview.to_px(toolpath.start[sl][use][:, :2]) * (1 << shift)).astype(np.int64)
    p1 = np.round(topview.to_px(toolpath.end[sl][use][:, :2]) * (1 << shift)).astype(np.int64)
    thick = np.maximum(1, np.round(toolpath.width[sl][use] * topview.px_per_mm)).astype(int)
    for a, b, t in zip(p0.tolist(), p1.tolist(), thick.tolist(), strict=True):
        cv2.line(out, (a[0], a[1]), (b[0], b[1]), 1, int(t), cv2.LINE_8, shift)
    return out.astype(bool)


def run_axes(labels: np.ndarray, n: int, coords_mm: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Length (mm) and principal axis (radians) of each labelled run on the bed.

    The length is the extent of the run's pixels' bed coordinates along their
    principal axis: a run along a straight wall reads as its length, along a
    curved wall as its chord, a blob as about its diameter.

    Parameters
    ----------
    labels : ndarray, int32, shape (h, w)
        Run labels, 0: none.
    n : int
        Number of labels (0 included).
    coords_mm : (ndarray, ndarray), float, shape (h, w) each
        Bed ``x`` and ``y`` (mm) of every pixel on the layer's plane.

    Returns
    -------
    length : ndarray, float64, shape (n,)
        0 for label 0 and for labels without pixels.
    theta : ndarray, float64, shape (n,)
        Angle of the principal axis from the bed's ``x`` axis, radians in [-pi/2, pi/2].
    """
    on = np.flatnonzero(labels.ravel())
    lab = labels.ravel()[on]
    x, y = (np.asarray(c, np.float64).ravel()[on] for c in coords_mm)
    cnt = np.maximum(np.bincount(lab, minlength=n), 1).astype(np.float64)
    dx, dy = x - (np.bincount(lab, x, n) / cnt)[lab], y - (np.bincount(lab, y, n) / cnt)[lab]
    sxx, syy, sxy = (np.bincount(lab, v, n) for v in (dx * dx, dy * dy, dx * dy))
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # the principal axis of each run
    p = dx * np.cos(theta)[lab] + dy * np.sin(theta)[lab]
    lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(lo, lab, p)
    np.maximum.at(hi, lab, p)
    out = np.where(np.isfinite(lo), hi - lo, 0.0)
    out[0] = 0.0
    return out, theta


def run_lengths(labels: np.ndarray, n: int, coords_mm: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Length (mm) of each labelled run (:func:`run_axes`), shape ``(n,)``, 0 for label 0."""
    return run_axes(labels, n, coords_mm)[0]


def ray_angles(labels: np.ndarray, n: int, theta: np.ndarray, ray: np.ndarray) -> np.ndarray:
    """Angle (degrees, 0-90) between each run's axis and the mean horizontal direction of its pixels' rays.

    Parameters
    ----------
    labels : ndarray, int32, shape (h, w)
    n : int
    theta : ndarray, float64, shape (n,)
        The runs' axes (:func:`run_axes`), radians in the bed's ``x``/``y`` frame.
    ray : ndarray, float, shape (2, h, w)
        Per pixel, the bed ``x``/``y`` displacement of its ray per mm of height (any positive
        scale, the same axes as the bed coordinates: ``B`` of
        :func:`~layerwatch.analysis.scene_change.plane_maps`).

    Returns
    -------
    ndarray, float64, shape (n,)
        90 where a run's rays have no horizontal direction (a camera straight above).
    """
    on = np.flatnonzero(labels.ravel())
    lab = labels.ravel()[on]
    rx, ry = (np.bincount(lab, np.asarray(ray[k], np.float64).ravel()[on], n) for k in (0, 1))
    norm = np.hypot(rx, ry)
    cos = np.abs(np.cos(theta) * rx + np.sin(theta) * ry) / np.maximum(norm, 1e-12)
    return np.where(norm > 1e-12, np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))), 90.0)


def wall_runs(candidates: np.ndarray, walls: np.ndarray, coords_mm: tuple[np.ndarray, np.ndarray],
              min_length_mm: float, bridge_px: int = WALL_BRIDGE_PX, ray: np.ndarray | None = None,
              min_angle_deg: float = MIN_RAY_ANGLE_DEG) -> np.ndarray:
    """The candidate perimeter pixels that lie in a run along the wall at least ``min_length_mm`` long,
    across the line of sight.

    Parameters
    ----------
    candidates : ndarray, bool, shape (h, w)
        Perimeter pixels that look as in the previous photo (working image).
    walls : ndarray, bool, shape (h, w)
        The layer's perimeters projected into the working image (:func:`wall_top`).
    coords_mm : (ndarray, ndarray), float, shape (h, w) each
        Bed coordinates (mm) of every pixel on the layer's plane.
    min_length_mm : float
        Shortest run kept.
    bridge_px : int
        Candidates this close along the perimeter join one run (a pixel or two
        of the gap read as changed does not cut it in two).
    ray : ndarray, float, shape (2, h, w), optional
        Horizontal direction of each pixel's ray (:func:`ray_angles`); a run whose axis lies within
        ``min_angle_deg`` of it is not kept (module notes). ``None``: no such test.
    min_angle_deg : float

    Returns
    -------
    ndarray, bool, shape (h, w)
        The kept candidates.
    """
    cand = candidates & walls
    if not cand.any():
        return cand
    grp = cand
    if bridge_px > 0:
        k = np.ones((2 * bridge_px + 1, 2 * bridge_px + 1), np.uint8)
        grp = (cv2.dilate(cand.astype(np.uint8), k) > 0) & walls
    n, lab = cv2.connectedComponents(grp.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(cand)
    length, theta = run_axes(lab, n, coords_mm)
    keep = length >= min_length_mm
    if ray is not None and min_angle_deg > 0:
        keep &= ray_angles(lab, n, theta, ray) >= min_angle_deg
    keep[0] = False
    return cand & keep[lab]


def wall_verdict(change: WindowChange, surface: np.ndarray, walls: np.ndarray, parallax: tuple[float, float],
                 coords_mm: tuple[np.ndarray, np.ndarray], settings: LayerChangeSettings,
                 ray: np.ndarray | None = None, exclude: np.ndarray | None = None) -> np.ndarray:
    """The channel's unchanged pixels plus the long runs of looser candidates along the perimeters (module notes).

    ``change.unchanged`` stands. On the perimeters a judged pixel is a
    candidate when ``same >= wall_min_ncc`` and ``same - twin >= wall_min_gain``
    and it is not in a silhouette band (:func:`~layerwatch.analysis.layer_change.drop_edge_slivers`);
    the candidates in runs of at least ``wall_run_mm`` across the line of sight (:func:`wall_runs`)
    are added. Pixels already out of ``change.judged`` (:mod:`~layerwatch.analysis.seen_past`'s blind
    band) are never candidates.

    Parameters
    ----------
    change : WindowChange
        :func:`~layerwatch.analysis.layer_change.window_change` of the photo pair.
    surface : ndarray, bool, shape (h, w)
        The new layer's footprint on its plane, seen through the camera.
    walls : ndarray, bool, shape (h, w)
        The layer's perimeters, projected the same way (:func:`wall_top`).
    parallax : (float, float)
        Image shift of the height printed since the previous photo, px.
    coords_mm : (ndarray, ndarray), float, shape (h, w) each
        Bed coordinates (mm) of every pixel on the layer's plane.
    settings : LayerChangeSettings
    ray : ndarray, float, shape (2, h, w), optional
        Horizontal direction of each pixel's ray (``B`` of
        :func:`~layerwatch.analysis.scene_change.plane_maps`); ``None``: runs along the line of
        sight count too.
    exclude : ndarray, bool, shape (h, w), optional
        Pixels that are no candidates (the pipeline: :data:`WALL_BLIND_SHARE` of the window's
        previous texture seen past the part).

    Returns
    -------
    ndarray, bool, shape (h, w)
    """
    on = walls & surface
    if settings.wall_run_mm <= 0 or not on.any():
        return change.unchanged
    # on the surface's box: every candidate, run and footprint pixel the tests read lies in it (beyond it
    # the silhouette test's erosions read the footprint's zeros either way), so the result is the whole image's
    u, v, w, h = cv2.boundingRect(np.ascontiguousarray(surface).view(np.uint8))
    box = (slice(v, v + h), slice(u, u + w))
    on = on[box]
    same, twin = change.same[box], change.twin[box]
    cand = on & change.judged[box] & (same >= settings.wall_min_ncc) & (same - twin >= settings.wall_min_gain)
    if exclude is not None:
        cand &= ~exclude[box]
    sig = float(settings.window_px)
    cand = drop_edge_slivers(cand, surface[box], parallax, int(round(2 * sig)), max(1, int(round(EDGE_DEPTH * sig))))
    runs = wall_runs(cand, on, (coords_mm[0][box], coords_mm[1][box]), settings.wall_run_mm,
                     ray=None if ray is None else np.asarray(ray)[:, box[0], box[1]])
    out = change.unchanged.copy()
    out[box] |= runs
    return out
