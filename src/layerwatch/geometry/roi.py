"""The region of interest of a calibrated camera: the photo box that the bed's observed square and the print cover.

A printer's camera sees more than the bed: the frame, the room, the ceiling. What the
checks judge (the print, its layers, the bed markers) lies in the box that the observed
square on the bed and the print's prism (its reach, from the bed to its top) cover, which
the camera's pose gives once per job. :func:`bed_roi` computes it; the camera-fault gate
measures its noise, blocking and repeat figures there
(:class:`~layerwatch.monitor.frame_checks.FrameChecks`): 0.51-0.60 of the frame with the
simulator's camera at 30-60 degrees and the example part, with the bed markers and the margin.

The box is aligned to :data:`ROI_ALIGN` px: its start is on the 8-px JPEG block grid (the
blocking figure reads steps at a block's edge) and on a whole number of the gate's reduction
factor at the common frame sizes (x2 at 1280 px, x3 at 1920 px, x6 at 3840 px), so the
reduced box is the box of the reduced frame, pixel for pixel.
"""

from __future__ import annotations

import numpy as np

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.synthetic import project_points
from layerwatch.geometry.topview import TopView

__all__ = ["REACH_PAD_MM", "ROI_ALIGN", "ROI_MARGIN", "bed_roi"]

#: the box's start (and, inside the frame, its end) is a multiple of this, px (lcm of 8, 2, 3, 6 and 16)
ROI_ALIGN = 48
#: the box is grown by this share of the frame's diagonal on every side, before the alignment (the lens model's
#: error, a bumped camera's first frames, the bed markers' dots)
ROI_MARGIN = 0.01
#: points sampled along each edge of the observed square (the lens bends the edges)
_EDGE_POINTS = 17
#: the print's reach is grown by this on every side, mm (as the checks' prism, :mod:`layerwatch.pipeline.checks`)
REACH_PAD_MM = 2.0


def _edges(corners: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points along the closed polygon ``corners`` (K, 2), ``len(t)`` per edge, shape (K len(t), 2)."""
    return np.vstack([a + t * (b - a) for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True)])


def bed_roi(camera: CameraModel, topview: TopView, top_z_mm: float, size: tuple[int, int],
            extra_px: np.ndarray | None = None,
            reach_mm: tuple[float, float, float, float] | None = None) -> tuple[slice, slice]:
    """The photo box (rows, columns) that the observed square on the bed and the print up to ``top_z_mm`` cover.

    Parameters
    ----------
    camera : CameraModel
        With its bed pose (calibrated at any size of the same aspect ratio).
    topview : TopView
        The observed square (``corners_mm``).
    top_z_mm : float
        The print's highest point, mm.
    size : (int, int)
        ``(width, height)`` of the frames, px.
    extra_px : ndarray, shape (K, 2), optional
        Further points the box must hold, px at ``size`` (the bed markers' expected centres).
    reach_mm : (float, float, float, float), optional
        ``(xmin, ymin, xmax, ymax)`` bed mm the print covers (:func:`~layerwatch.pipeline.checks.print_reach_mm`):
        its prism, grown by :data:`REACH_PAD_MM`, from the bed to ``top_z_mm`` (the square itself is taken at
        Z = 0: what lies beside the print lies on the bed). Without it the whole square is taken up to
        ``top_z_mm`` (a tall print's square at its top covers most of a 45-degree camera's frame).

    Returns
    -------
    (slice, slice)
        Rows and columns of the box: grown by :data:`ROI_MARGIN` of the diagonal, aligned outward to
        :data:`ROI_ALIGN` px, clipped to the frame. The whole frame when nothing projects into it
        (a pose that does not see the bed) or ``top_z_mm`` is not finite.
    """
    w, h = (int(v) for v in size)
    whole = (slice(0, h), slice(0, w))
    if not np.isfinite(top_z_mm) or not camera.has_pose:
        return whole
    cam = camera.scaled_to((w, h))
    corners = np.asarray(topview.corners_mm, np.float64).reshape(-1, 2)
    t = np.linspace(0.0, 1.0, _EDGE_POINTS)[:, None]
    edges = _edges(corners, t)
    high = edges
    if reach_mm is not None and np.all(np.isfinite(reach_mm)):
        x0, y0, x1, y1 = (float(v) for v in reach_mm)
        p = REACH_PAD_MM
        high = _edges(np.array([[x0 - p, y0 - p], [x1 + p, y0 - p], [x1 + p, y1 + p], [x0 - p, y1 + p]]), t)
    pts = np.vstack([np.c_[edges, np.zeros(len(edges))], np.c_[high, np.zeros(len(high))],
                     np.c_[high, np.full(len(high), float(top_z_mm))]])
    # a point behind the camera projects to nonsense: only points in front count
    T = cam.camera_from_bed
    in_front = (T[:3, :3] @ pts.T + T[:3, 3:4])[2] > 0
    uv = project_points(cam, pts[in_front]) if in_front.any() else np.zeros((0, 2))
    if extra_px is not None:
        uv = np.vstack([uv, np.asarray(extra_px, np.float64).reshape(-1, 2)])
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if len(uv) == 0:
        return whole
    grow = ROI_MARGIN * float(np.hypot(w, h))
    x0, y0 = np.floor(uv.min(axis=0) - grow)
    x1, y1 = np.ceil(uv.max(axis=0) + grow)
    if x1 < 0 or y1 < 0 or x0 >= w or y0 >= h:
        return whole
    a = ROI_ALIGN
    c0, r0 = max(int(x0) // a * a, 0), max(int(y0) // a * a, 0)
    c1, r1 = min(-(-int(x1) // a) * a, w), min(-(-int(y1) // a) * a, h)
    return (slice(r0, r1), slice(c0, c1))
