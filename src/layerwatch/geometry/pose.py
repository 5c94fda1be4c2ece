"""Camera pose from the bed markers, and a check that the camera has not moved.

``camera_from_bed`` is solved with :func:`cv2.solvePnPGeneric` using IPPE
(the markers are coplanar), keeping only physically plausible solutions:
camera above the bed, every marker in front of it, small reprojection error.

Marker ordering (dots carry no identity): the markers are assumed to be in
convex position. For every choice of ``n`` candidate blobs, the blobs are
ordered around their centroid and paired with the layout ordered the same
way, trying both orientations and all ``n`` cyclic shifts; each pairing is
solved and scored by reprojection error. A mirrored pairing puts the camera
under the bed and is refused. A symmetric layout (the default square) fits
equally well in ``n`` rotations; among pairings whose error is close to the
best, the one whose camera azimuth is closest to
``MarkerSettings.camera_azimuth_deg`` (default: in front of the printer) is
taken. Use ArUco markers when the camera may stand anywhere.

References
----------
Petsiuk & Pearce (2022), eq. (1); Collins & Bartoli (2014), IPPE.
"""

from __future__ import annotations

import datetime as _dt
import logging
from dataclasses import dataclass, replace
from itertools import combinations

import cv2
import numpy as np

from layerwatch.errors import MarkerError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.markers import detect_aruco, detect_dots, photo_problem
from layerwatch.geometry.synthetic import project_points

__all__ = ["solve_pose", "locate_bed", "camera_moved", "MoveCheck", "marker_layout", "reprojection_rms"]

log = logging.getLogger(__name__)


def marker_layout(markers, topview) -> np.ndarray:
    """Marker bed positions (n, 2) mm: ``markers.positions_mm`` or the observed square's corners."""
    pos = getattr(markers, "positions_mm", None)
    p = np.asarray(pos if pos is not None else topview.corners_mm, dtype=np.float64).reshape(-1, 2)
    if len(p) < 4:
        raise MarkerError(f"the marker layout has {len(p)} positions; configure at least 4 in [markers] positions_mm.")
    return p


def _obj(markers_mm: np.ndarray) -> np.ndarray:
    m = np.asarray(markers_mm, dtype=np.float64).reshape(-1, 2)
    return np.c_[m, np.zeros(len(m))]


def reprojection_rms(camera: CameraModel, rvec, tvec, image_points, markers_mm) -> float:
    """RMS distance (px) between ``image_points`` (n, 2) and the projected markers."""
    uv = cv2.projectPoints(_obj(markers_mm), np.asarray(rvec, float), np.asarray(tvec, float),
                           camera.K, camera.dist)[0].reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum((uv - np.asarray(image_points, float)) ** 2, axis=1))))


def _plausible(rvec, tvec, obj) -> str | None:
    R = cv2.Rodrigues(rvec)[0]
    C = -R.T @ tvec.reshape(3)
    if C[2] <= 1.0:
        return "the camera would be below the bed"
    depth = (obj @ R.T + tvec.reshape(1, 3))[:, 2]
    if np.any(depth <= 1.0):
        return "a marker would be behind the camera"
    return None


def _candidates(camera, image_points, obj):
    """Plausible ``(rms, rvec, tvec)`` IPPE solutions for one pairing."""
    img = np.asarray(image_points, np.float64).reshape(-1, 1, 2)
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj.reshape(-1, 1, 3), img, camera.K, camera.dist,
                                                    flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return []
    out = []
    for r, t in zip(rvecs, tvecs, strict=True):
        if _plausible(r, t, obj) is None:
            out.append((reprojection_rms(camera, r, t, image_points, obj[:, :2]), r.reshape(3), t.reshape(3)))
    return out


def _disc_bias(camera, rvec, tvec, markers_mm, radius_mm, *, areas: bool = False) -> np.ndarray:
    """Area centroid of each imaged disc minus the image of its centre, (n, 2) px (or the areas, (n,) px²)."""
    a = np.linspace(0, 2 * np.pi, 96, endpoint=False)
    out = []
    for m in np.asarray(markers_mm, float):
        ring = np.c_[m[0] + radius_mm * np.cos(a), m[1] + radius_mm * np.sin(a), np.zeros_like(a)]
        pts = cv2.projectPoints(np.vstack([[m[0], m[1], 0.0], ring]), rvec, tvec, camera.K, camera.dist)[0].reshape(-1, 2)
        c, poly = pts[0], pts[1:]
        x, y = poly[:, 0], poly[:, 1]
        xs, ys = np.roll(x, -1), np.roll(y, -1)
        cr = x * ys - xs * y
        A = cr.sum() / 2
        out.append(abs(A) if areas else np.array([((x + xs) * cr).sum(), ((y + ys) * cr).sum()]) / (6 * A) - c)
    return np.array(out)


def solve_pose(camera: CameraModel, image_points, markers_mm, *, max_error_px: float = 3.0,
               marker_radius_mm: float | None = None) -> CameraModel:
    """Solve ``camera_from_bed`` from ordered marker observations.

    Parameters
    ----------
    camera : CameraModel
        Intrinsics for the photo's resolution.
    image_points : ndarray, shape (n, 2)
        Observed (distorted) marker centres, px, in the order of ``markers_mm``.
    markers_mm : ndarray, shape (n, 2)
        Marker bed coordinates (Z = 0), mm; ``n >= 4``.
    max_error_px : float
        Refuse poses whose RMS reprojection error exceeds this.
    marker_radius_mm : float or None
        When given, ``image_points`` are disc area centroids and their
        perspective bias is removed (one iteration).

    Returns
    -------
    CameraModel
        ``camera`` with ``rvec``, ``tvec``, ``markers_mm`` and
        ``errors["pose_px"]`` set.

    Raises
    ------
    MarkerError
        Too few points, or no plausible pose within ``max_error_px``.
    """
    img = np.asarray(image_points, np.float64).reshape(-1, 2)
    obj = _obj(markers_mm)
    if len(img) != len(obj) or len(img) < 4:
        raise MarkerError(f"need the same number (>= 4) of image points and marker positions, got {len(img)} and {len(obj)}.")
    sols = _candidates(camera, img, obj)
    if not sols:
        raise MarkerError("the markers give no plausible camera pose (camera below the bed or behind a marker); check the marker layout in [markers].")
    rms, r, t = min(sols, key=lambda s: s[0])
    if marker_radius_mm:
        fixed = img - _disc_bias(camera, r, t, obj[:, :2], marker_radius_mm)
        r2, t2 = cv2.solvePnPRefineLM(obj.reshape(-1, 1, 3), fixed.reshape(-1, 1, 2), camera.K, camera.dist,
                                      r.reshape(3, 1).copy(), t.reshape(3, 1).copy())
        r, t = r2.reshape(3), t2.reshape(3)
        rms = reprojection_rms(camera, r, t, fixed, obj[:, :2])
    else:
        r2, t2 = cv2.solvePnPRefineLM(obj.reshape(-1, 1, 3), img.reshape(-1, 1, 2), camera.K, camera.dist,
                                      r.reshape(3, 1).copy(), t.reshape(3, 1).copy())
        r, t = r2.reshape(3), t2.reshape(3)
        rms = reprojection_rms(camera, r, t, img, obj[:, :2])
    why = _plausible(r, t, obj)
    if why:
        raise MarkerError(f"the marker pose is implausible: {why}; check the marker layout in [markers].")
    if not rms <= max_error_px:
        raise MarkerError(f"the markers do not fit the configured layout (reprojection error {rms:.1f} px > {max_error_px:g} px); check [markers] positions_mm and that no marker is covered.")
    errors = dict(camera.errors)
    errors["pose_px"] = rms
    return replace(camera, rvec=r, tvec=t, markers_mm=obj[:, :2].copy(), errors=errors)


def _azimuth(rvec, tvec, centre) -> float:
    R = cv2.Rodrigues(np.asarray(rvec, float))[0]
    C = -R.T @ np.asarray(tvec, float)
    return float(np.arctan2(C[1] - centre[1], C[0] - centre[0]))


def _ccw(points: np.ndarray) -> np.ndarray:
    c = points.mean(0)
    return np.argsort(np.arctan2(points[:, 1] - c[1], points[:, 0] - c[0]))


def match_dots(camera: CameraModel, blobs, layout_mm: np.ndarray, *, azimuth_deg: float = -90.0,
               max_error_px: float = 3.0, max_candidates: int = 8):
    """Choose and order ``n = len(layout_mm)`` of the blob centres; returns ``(image_points (n, 2), rms)``."""
    n = len(layout_mm)
    pts = np.array([b.center for b in blobs[:max_candidates]], dtype=np.float64).reshape(-1, 2)
    if len(pts) < n:
        raise MarkerError(f"found {len(pts)} of the {n} bed markers; make sure all white dots are visible, lit and not covered.")
    obj = _obj(layout_mm)
    lay = _ccw(layout_mm)
    want = np.deg2rad(azimuth_deg)
    centre = layout_mm.mean(0)
    found = []  # (rms, subset, ordered points, azimuth error)
    for subset in combinations(range(len(pts)), n):
        sub = pts[list(subset)]
        order = _ccw(sub)
        for direction in (order, order[::-1]):
            for shift in range(n):
                ordered = np.empty((n, 2))
                ordered[lay] = sub[np.roll(direction, shift)]
                for rms, r, t in _candidates(camera, ordered, obj):
                    daz = abs((_azimuth(r, t, centre) - want + np.pi) % (2 * np.pi) - np.pi)
                    found.append((rms, frozenset(subset), ordered, daz))
    good = [f for f in found if f[0] <= max_error_px * 2]
    if not good:
        raise MarkerError(f"no {n} of the {len(pts)} bright dots fit the marker layout; check [markers] positions_mm and that no marker is covered.")
    best = min(f[0] for f in good)
    close = [f for f in good if f[0] <= 2 * best + 0.5]
    if len({f[1] for f in close}) > 1:
        raise MarkerError("more bright dots than markers fit the layout (duplicated marker?); cover or remove the extra dot.")
    pick = min(close, key=lambda f: f[3])
    return pick[2], pick[0]


def _check_dot_sizes(cam, blobs, pts, layout, radius_mm, limit: float = 2.0) -> None:
    """Refuse a dot whose imaged area is far from what the pose predicts (glare, a covering object)."""
    want = _disc_bias(cam, cam.rvec, cam.tvec, layout, radius_mm, areas=True)
    centres = np.array([b.center for b in blobs])
    for k, p in enumerate(pts):
        got = blobs[int(np.argmin(np.linalg.norm(centres - p, axis=1)))].area
        ratio = got / max(want[k], 1e-9)
        if not 1 / limit <= ratio <= limit:
            x, y = layout[k]
            raise MarkerError(f"the marker at bed ({x:g}, {y:g}) mm looks {ratio:.1f}x its expected size "
                              "(glare, a reflection or something covering it); fix the lighting or clear the marker.")


def locate_bed(camera: CameraModel, photo: np.ndarray, markers, topview) -> CameraModel:
    """Find the bed markers in a photo and return ``camera`` with its bed pose.

    Parameters
    ----------
    camera : CameraModel
        Intrinsics (pose not needed); any resolution with the photo's aspect.
    photo : ndarray, uint8, shape (h, w[, 3])
        BGR photo of the bed with all markers visible.
    markers : MarkerSettings
        Kind, positions (default: ``topview`` corners), diameter, cues.
    topview : TopView
        Gives the default marker layout.

    Returns
    -------
    CameraModel
        Same ``K``/``image_size`` as ``camera``, with ``rvec``, ``tvec``,
        ``markers_mm``, ``marker_kind`` and ``errors["pose_px"]`` (px of the photo).

    Raises
    ------
    MarkerError
        Markers missing, duplicated, or the pose is implausible; the message
        says what to fix (and whether the photo is blurred/overexposed).
    """
    h, w = photo.shape[:2]
    cam = camera.scaled_to((w, h))
    layout = marker_layout(markers, topview)
    try:
        if markers.kind == "aruco":
            found = detect_aruco(photo, markers.aruco_dictionary)
            missing = [i for i in range(len(layout)) if i not in found]
            if missing:
                raise MarkerError(f"ArUco ids {missing} not found in the photo; make sure every tag is visible.")
            pts = np.array([found[i] for i in range(len(layout))])
            posed = solve_pose(cam, pts, layout, max_error_px=markers.max_pose_error_px)
        else:
            blobs = detect_dots(photo)
            pts, _ = match_dots(cam, blobs, layout, azimuth_deg=markers.camera_azimuth_deg,
                                max_error_px=markers.max_pose_error_px)
            posed = solve_pose(cam, pts, layout, max_error_px=markers.max_pose_error_px,
                               marker_radius_mm=markers.diameter_mm / 2.0)
            _check_dot_sizes(posed, blobs, pts, layout, markers.diameter_mm / 2.0)
    except MarkerError as exc:
        why = photo_problem(photo)
        if why:
            raise MarkerError(f"{str(exc).rstrip('.')} ({why}).") from None
        raise

    return replace(camera, rvec=posed.rvec, tvec=posed.tvec, markers_mm=layout.copy(),
                   marker_kind=markers.kind, errors={**camera.errors, "pose_px": posed.errors["pose_px"]},
                   created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"))


@dataclass(frozen=True)
class MoveCheck:
    """Result of :func:`camera_moved`: ``moved``, largest marker shift (px), and a message."""

    moved: bool
    shift_px: float
    message: str


def camera_moved(camera: CameraModel, photo: np.ndarray, markers=None, topview=None, *,
                 tolerance_px: float | None = None) -> MoveCheck:
    """Check that the markers are where the saved pose predicts.

    Each marker's predicted position (saved pose, photo resolution) is
    matched to the nearest detected dot (or ArUco tag). ``moved`` is True
    when any marker is farther than ``tolerance_px`` (default: 0.4 % of the
    image diagonal, at least 3 px) or at most half of them are found; a
    warning is logged then. Never raises on a bad photo.
    """
    if not camera.has_pose or camera.markers_mm is None:
        return MoveCheck(True, float("inf"), "the camera model has no saved marker pose; recalibrate with --markers.")
    h, w = photo.shape[:2]
    try:
        cam = camera.scaled_to((w, h))
        pred = project_points(cam, camera.markers_mm)
        kind = getattr(markers, "kind", camera.marker_kind)
        if kind == "aruco":
            found = detect_aruco(photo, getattr(markers, "aruco_dictionary", "DICT_4X4_50"))
            seen = np.array([v for _, v in sorted(found.items())]).reshape(-1, 2)
        else:
            seen = np.array([b.center for b in detect_dots(photo, max_candidates=20)]).reshape(-1, 2)
    except Exception as exc:  # noqa: BLE001 - a check must not crash the monitor
        return MoveCheck(True, float("inf"), f"could not check the camera position: {exc}")
    tol = tolerance_px if tolerance_px is not None else max(3.0, 0.004 * float(np.hypot(w, h)))
    search = 0.08 * float(np.hypot(w, h))
    d = np.full(len(pred), np.inf)
    if len(seen):
        d = np.min(np.linalg.norm(pred[:, None, :] - seen[None, :, :], axis=2), axis=1)
    near = d[d <= search]
    if len(near) <= len(pred) // 2:
        check = MoveCheck(True, float("inf"), "the bed markers are not where the saved pose predicts; the camera has probably moved: recalibrate with `layerwatch calibrate --markers`.")
    else:
        shift = float(near.max())
        moved = shift > tol
        msg = (f"markers are {shift:.1f} px from the saved pose; the camera has moved: recalibrate with `layerwatch calibrate --markers`."
               if moved else f"camera in place (markers within {shift:.1f} px).")
        check = MoveCheck(moved, shift, msg)
    if check.moved:
        log.warning(check.message)
    return check
