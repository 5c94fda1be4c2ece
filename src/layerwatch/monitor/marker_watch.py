"""A camera that moved: the calibration's bed markers, where a frame should show them and where it does.

With a calibration that recorded the bed markers (``CameraModel.markers_mm``),
each frame's markers are compared with the calibration's projection at the
frame's size (:func:`~layerwatch.analysis.frame_quality.marker_shift_px`, in
the camera-fault gate): visible markers away from their place are a camera
fault; markers hidden (by spaghetti, the head, a part) give no verdict.

**Detection** (:meth:`MarkerWatch.found_px`): the dots on a copy at most
:data:`MARKER_SIDE_PX` px wide, the centres refined at full size
(:func:`~layerwatch.geometry.markers.detect_dots`), or the ArUco tags.

**Confirmation first** (dots): a camera that did not move shows its dots where
they were, so each frame first *confirms* them in place
(:func:`~layerwatch.geometry.markers.confirm_dots`: each dot refined in a box of
its own size plus :attr:`MarkerWatch.confirm_px` around its expected centre,
with the area the last detection measured), a few small boxes instead of the
whole frame. When a strict majority of the dots is confirmed, those centres are
the frame's markers: every one within ``confirm_px`` (:data:`CONFIRM_SHARE` of the
gate's ``max_marker_shift_px``) of its place, so the gate's median shift passes, as
the full detection's would (it finds the same dots, refined the same way, and
any false candidates near the other dots are a minority, below the median).
Otherwise (the camera moved, dots hidden, glare, the first frame) the full
detection runs and its verdict is the gate's, as without the confirmation; it
also learns the dots' areas.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.markers import confirm_dots, detect_aruco, detect_dots
from layerwatch.geometry.synthetic import project_points

__all__ = ["MarkerWatch", "CONFIRM_SHARE", "MARKER_SIDE_PX"]

#: longest side of the copy the dot markers are looked for in, px (centres are refined at full size)
MARKER_SIDE_PX = 960
#: dots within this share of the gate's ``max_marker_shift_px`` of their places are confirmed in place
CONFIRM_SHARE = 0.5


class MarkerWatch:
    """The calibration's bed markers: where a frame should show them, and where it does (module notes).

    Parameters
    ----------
    camera : CameraModel
        Calibrated with markers (``markers_mm`` and a pose).
    kind : {"dots", "aruco"}
        Marker kind (default: the camera model's).
    dictionary : str
        ArUco dictionary for ``kind="aruco"``.
    confirm_px : float
        Dots found within this distance of their places (px at the frame's size) confirm the
        camera did not move without the full detection (:meth:`of_pipeline`: :data:`CONFIRM_SHARE`
        of the gate's ``max_marker_shift_px``; 0: always the full detection).
    """

    def __init__(self, camera: CameraModel, kind: str | None = None, dictionary: str = "DICT_4X4_50",
                 confirm_px: float = 0.0) -> None:
        if not camera.has_pose or camera.markers_mm is None:
            raise ValueError("the camera model has no marker pose; calibrate with --markers")
        if not (np.isfinite(confirm_px) and confirm_px >= 0):
            raise ValueError(f"confirm_px = {confirm_px} must be a finite number >= 0 (px)")
        self.camera, self.dictionary = camera, dictionary
        self.kind = kind or camera.marker_kind or "dots"
        self.confirm_px = float(confirm_px)
        self._expected: dict[tuple[int, int], np.ndarray] = {}
        #: each dot's area as the last full detection measured it at a frame size, px^2 (NaN: not seen in place)
        self._areas: dict[tuple[int, int], np.ndarray] = {}
        #: frames whose dots were confirmed in place / that ran the full detection (for tests and profiles)
        self.confirmed = self.detected = 0

    @classmethod
    def of_pipeline(cls, pipeline: Any, max_shift_px: float = 0.0) -> MarkerWatch | None:
        """The watch for a pipeline's camera (``pipeline.camera``, ``pipeline.config.markers``), or None.

        ``max_shift_px``: the gate's ``max_marker_shift_px``; dots within :data:`CONFIRM_SHARE` of it
        are confirmed in place (0: the full detection on every frame).
        """
        cam = getattr(pipeline, "camera", None)
        if not isinstance(cam, CameraModel) or not cam.has_pose or cam.markers_mm is None:
            return None
        markers = getattr(getattr(pipeline, "config", None), "markers", None)
        return cls(cam, getattr(markers, "kind", None), getattr(markers, "aruco_dictionary", "DICT_4X4_50"),
                   CONFIRM_SHARE * max_shift_px)

    def expected_px(self, size: tuple[int, int]) -> np.ndarray:
        """Marker centres the calibration predicts in a frame of ``size`` = (w, h), shape (M, 2) px."""
        key = (int(size[0]), int(size[1]))
        if key not in self._expected:
            assert self.camera.markers_mm is not None  # checked in __init__
            self._expected[key] = project_points(self.camera.scaled_to(key), self.camera.markers_mm)
        return self._expected[key]

    def found_px(self, photo: np.ndarray) -> np.ndarray:
        """Marker candidates detected in ``photo`` (BGR or grey), shape (K, 2) px (K may be 0)."""
        return self._detect(photo)[0]

    def _detect(self, photo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The full detection: candidates (K, 2) px and their areas (K,) px^2 (NaN for ArUco tags)."""
        if self.kind == "aruco":
            found = detect_aruco(photo, self.dictionary)
            centres = np.array([v for _, v in sorted(found.items())], np.float64).reshape(-1, 2)
            return centres, np.full(len(centres), np.nan)
        blobs = detect_dots(photo, max_candidates=20, max_side_px=MARKER_SIDE_PX)
        return (np.array([b.center for b in blobs], np.float64).reshape(-1, 2),
                np.array([b.area for b in blobs], np.float64))

    def _confirmed(self, photo: np.ndarray, key: tuple[int, int], expected: np.ndarray) -> np.ndarray | None:
        """The dots confirmed in place when a strict majority is (module notes), else None."""
        areas = self._areas.get(key)
        if self.kind != "dots" or self.confirm_px <= 0 or areas is None or len(expected) < 2:
            return None
        centres = confirm_dots(photo, expected, areas, self.confirm_px)
        ok = np.isfinite(centres[:, 0])
        return centres[ok] if 2 * int(ok.sum()) > len(expected) else None

    def _learn(self, key: tuple[int, int], expected: np.ndarray, found: np.ndarray, areas: np.ndarray) -> None:
        """Keep the area of each dot the full detection found within ``confirm_px`` of its place."""
        if self.kind != "dots" or self.confirm_px <= 0 or len(found) == 0:
            return
        known = self._areas.setdefault(key, np.full(len(expected), np.nan))
        d = np.linalg.norm(expected[:, None, :] - found[None, :, :], axis=2)
        nearest = d.argmin(axis=1)
        here = d[np.arange(len(expected)), nearest] <= self.confirm_px
        known[here] = areas[nearest[here]]

    def __call__(self, photo: np.ndarray) -> dict[str, np.ndarray]:
        """``markers_px`` and ``expected_markers_px`` for :func:`assess_frame` (at the photo's size).

        ``photo``: the frame, BGR, or its grey image (the gate's, converted once).
        """
        h, w = photo.shape[:2]
        key = (int(w), int(h))
        expected = self.expected_px(key)
        found = self._confirmed(photo, key, expected)
        if found is not None:
            self.confirmed += 1
            return {"markers_px": found, "expected_markers_px": expected}
        self.detected += 1
        found, areas = self._detect(photo)
        self._learn(key, expected, found, areas)
        return {"markers_px": found, "expected_markers_px": expected}
