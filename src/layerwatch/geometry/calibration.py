"""Camera intrinsics: from photos of a chessboard / ChArUco board, or a field-of-view guess.

References
----------
Zhang (2000), a flexible technique for camera calibration (as implemented by
:func:`cv2.calibrateCamera`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from layerwatch.errors import CalibrationError
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.markers import _aruco_dictionary, to_grey

__all__ = ["BoardSpec", "find_board", "calibrate_intrinsics", "approximate_intrinsics", "read_photo"]


@dataclass(frozen=True)
class BoardSpec:
    """A calibration target.

    Parameters
    ----------
    kind : {"chessboard", "charuco"}
    cols, rows : int
        Chessboard: inner corners per row / column (``9x6`` for a 10 x 7
        squares board). ChArUco: squares along x / y.
    square_mm : float
        Side of one square, mm.
    marker_mm : float
        ChArUco only: side of the ArUco tags, mm (default 0.75 square).
    dictionary : str
        ChArUco only: ArUco dictionary name.
    """

    kind: str = "chessboard"
    cols: int = 9
    rows: int = 6
    square_mm: float = 25.0
    marker_mm: float | None = None
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "charuco"):
            raise CalibrationError(f"unknown board kind {self.kind!r}; use 'chessboard' or 'charuco'.")
        if self.cols < 2 or self.rows < 2 or not self.square_mm > 0:
            raise CalibrationError(f"board {self.cols}x{self.rows} with {self.square_mm} mm squares is invalid; give e.g. --board-size 9x6 --square-mm 25.")

    def charuco(self):
        marker = self.marker_mm or 0.75 * self.square_mm
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_mm, marker,
                                      _aruco_dictionary(self.dictionary))


def read_photo(path: str | Path) -> np.ndarray:
    """Read an image file as BGR uint8 (h, w, 3); :class:`CalibrationError` when unreadable."""
    p = Path(path)
    img = cv2.imread(str(p), cv2.IMREAD_COLOR) if p.is_file() else None
    if img is None:
        raise CalibrationError(f"cannot read the photo {p}; pass PNG or JPEG files that exist.")
    return img


def find_board(photo: np.ndarray, board: BoardSpec) -> tuple[np.ndarray, np.ndarray] | None:
    """Detect the board: ``(object points (n, 3) mm, image points (n, 2) px)`` or None."""
    grey = to_grey(photo)
    if board.kind == "chessboard":
        size = (board.cols, board.rows)
        ok, corners = cv2.findChessboardCornersSB(grey, size, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        if not ok:
            ok, corners = cv2.findChessboardCorners(grey, size)
            if not ok:
                return None
            corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1),
                                       (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3))
        j, i = np.mgrid[0 : board.rows, 0 : board.cols]
        obj = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], -1) * board.square_mm
        return obj.astype(np.float64), corners.reshape(-1, 2).astype(np.float64)
    cb = board.charuco()
    det = cv2.aruco.CharucoDetector(cb)
    ch_corners, ch_ids, _, _ = det.detectBoard(grey)
    if ch_ids is None or len(ch_ids) < 6:
        return None
    obj, img = cb.matchImagePoints(ch_corners, ch_ids)
    return obj.reshape(-1, 3).astype(np.float64), img.reshape(-1, 2).astype(np.float64)


def calibrate_intrinsics(photos: Sequence, board: BoardSpec = BoardSpec(), *, min_views: int = 3,
                         progress=None) -> CameraModel:
    """Estimate ``K`` and distortion from several photos of a board.

    Parameters
    ----------
    photos : sequence of ndarray or path
        BGR images (or files) of the board in different poses, all the same size.
    board : BoardSpec
    min_views : int
        Minimum number of photos in which the board is found.
    progress : callable(done, total) or None

    Returns
    -------
    CameraModel
        Without pose; ``errors["intrinsics_px"]`` is the RMS reprojection
        error and ``errors["views"]`` the number of usable photos.

    Raises
    ------
    CalibrationError
        Mixed sizes, or fewer than ``min_views`` usable photos.
    """
    objs, imgs, size = [], [], None
    for k, ph in enumerate(photos):
        img = read_photo(ph) if isinstance(ph, (str, Path)) else ph
        s = (img.shape[1], img.shape[0])
        if size is None:
            size = s
        elif s != size:
            raise CalibrationError(f"calibration photos differ in size ({s} vs {size}); use one camera resolution.")
        found = find_board(img, board)
        if found is not None and len(found[0]) >= 6:
            objs.append(found[0].astype(np.float32))
            imgs.append(found[1].astype(np.float32))
        if progress is not None:
            progress(k + 1, len(photos))
    if len(objs) < min_views:
        raise CalibrationError(
            f"the {board.kind} ({board.cols}x{board.rows}) was found in {len(objs)} photo(s), "
            f"{min_views} are needed; check --board-size and take sharp photos of the whole board at varied angles.")
    assert size is not None  # photos were read: objs holds min_views (>= 1) views of the board
    flags = cv2.CALIB_FIX_K3 if len(objs) < 8 else 0
    rms, K, dist, _, _ = cv2.calibrateCamera(objs, imgs, size, None, None, flags=flags)
    if not np.isfinite(rms) or K[0, 0] <= 0:
        raise CalibrationError("calibration did not converge; take more photos with the board tilted in different directions.")
    return CameraModel(K=K, dist=dist.reshape(-1), image_size=size, approximate=False,
                       errors={"intrinsics_px": float(rms), "views": float(len(objs))})


def approximate_intrinsics(image_size: tuple[int, int], hfov_deg: float = 70.0) -> CameraModel:
    """Intrinsics guessed from the image size and a horizontal field of view (no board needed).

    Square pixels, principal point at the image centre, no distortion; the
    model is flagged ``approximate=True``.
    """
    w, h = (int(v) for v in image_size)
    if not 5.0 < hfov_deg < 175.0:
        raise CalibrationError(f"field of view {hfov_deg} deg is not plausible; give the horizontal FOV in degrees (e.g. 70).")
    f = (w / 2.0) / np.tan(np.deg2rad(hfov_deg) / 2.0)
    K = np.array([[f, 0, (w - 1) / 2.0], [0, f, (h - 1) / 2.0], [0, 0, 1.0]])
    return CameraModel(K=K, dist=np.zeros(5), image_size=(w, h), approximate=True,
                       errors={"hfov_deg": float(hfov_deg)})
