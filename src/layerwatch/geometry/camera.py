"""The camera model: intrinsics, distortion and bed pose, saved as one file.

Conventions (OpenCV): camera x right, y down, z forward. The pose maps bed
coordinates (mm) to camera coordinates: ``X_cam = R @ X_bed + t``
(``camera_from_bed``). ``K`` belongs to ``image_size``; use
:meth:`CameraModel.scaled_to` for photos of another size — it is the one
function that rescales ``K``.

References
----------
Petsiuk & Pearce (2022), eq. (1): ``s [u v 1]^T = K [R | t] [X Y Z 1]^T``.
"""

from __future__ import annotations

import datetime as _dt
import json
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import tomli_w

from layerwatch.errors import CalibrationError, ConfigError, WarpError

__all__ = ["CameraModel"]


def _arr(value, shape: tuple[int, ...] | None, name: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if shape is not None and a.shape != shape:
        raise ConfigError(f"camera model field '{name}' must have shape {shape}, got {a.shape}.")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"camera model field '{name}' contains NaN or inf.")
    return a


@dataclass
class CameraModel:
    """A calibrated camera looking at the bed.

    Attributes
    ----------
    K : ndarray, shape (3, 3)
        Intrinsic matrix for ``image_size``, pixels.
    dist : ndarray, shape (n,)
        OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3, ...])``.
    image_size : tuple of int
        ``(width, height)`` in pixels that ``K`` belongs to.
    rvec : ndarray, shape (3,) or None
        Rodrigues vector of ``R`` in ``camera_from_bed``; None before the pose
        is known.
    tvec : ndarray, shape (3,) or None
        Translation ``t`` of ``camera_from_bed``, mm.
    markers_mm : ndarray, shape (n, 2) or None
        Bed coordinates of the markers used for the pose, mm.
    marker_kind : str
        ``"dots"`` or ``"aruco"``.
    approximate : bool
        True when ``K`` is a field-of-view guess rather than a calibration.
    errors : dict
        Reprojection errors (``"intrinsics_px"``, ``"pose_px"``) in pixels.
    created : str
        ISO timestamp of the calibration.
    bed_photo : str or None
        The empty-bed photo kept with the model (``calibrate --markers``):
        written relative to the model file's folder when it lies there,
        read back as an absolute path; the scene channel's first expected
        appearance (:mod:`layerwatch.pipeline.scene`).
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    rvec: np.ndarray | None = None
    tvec: np.ndarray | None = None
    markers_mm: np.ndarray | None = None
    marker_kind: str = "dots"
    approximate: bool = False
    errors: dict[str, float] = field(default_factory=dict)
    created: str = field(
        default_factory=lambda: _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    )
    bed_photo: str | None = None

    def __post_init__(self) -> None:
        self.K = _arr(self.K, (3, 3), "K")
        self.dist = _arr(self.dist, None, "dist").reshape(-1)
        w, h = (int(v) for v in self.image_size)
        if w <= 0 or h <= 0:
            raise ConfigError(f"camera image_size must be positive, got {self.image_size}.")
        self.image_size = (w, h)
        if self.rvec is not None:
            self.rvec = _arr(self.rvec, None, "rvec").reshape(3)
        if self.tvec is not None:
            self.tvec = _arr(self.tvec, None, "tvec").reshape(3)
        if self.markers_mm is not None:
            self.markers_mm = _arr(self.markers_mm, None, "markers_mm")

    # ------------------------------------------------------------------ pose
    @property
    def has_pose(self) -> bool:
        return self.rvec is not None and self.tvec is not None

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """``(rvec, tvec)`` of ``camera_from_bed``, each shape (3,).

        Raises
        ------
        CalibrationError
            The model has no bed pose yet.
        """
        if self.rvec is None or self.tvec is None:
            raise CalibrationError(
                "the camera model has no bed pose yet: run `layerwatch calibrate --markers PHOTO`."
            )
        return self.rvec, self.tvec

    @property
    def R(self) -> np.ndarray:
        """Rotation of ``camera_from_bed``, shape (3, 3)."""
        if self.rvec is None:
            raise CalibrationError(
                "the camera model has no bed pose yet: run `layerwatch calibrate --markers PHOTO`."
            )
        return cv2.Rodrigues(self.rvec)[0]

    @property
    def camera_from_bed(self) -> np.ndarray:
        """Rigid transform, shape (4, 4), bed mm -> camera mm."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.tvec
        return T

    @property
    def center_mm(self) -> np.ndarray:
        """Camera centre in bed coordinates, mm, shape (3,)."""
        return -self.R.T @ self.tvec

    # ----------------------------------------------------------- resolution
    def scaled_to(self, image_size: tuple[int, int]) -> CameraModel:
        """Return the model for photos of another resolution.

        ``K`` is scaled per axis by the size ratio (pixel-edge convention:
        ``c' = (c + 0.5) * r - 0.5``); distortion and pose are unchanged.
        Refuses a different aspect ratio, which means a cropped stream.
        """
        w0, h0 = self.image_size
        w1, h1 = (int(v) for v in image_size)
        if (w1, h1) == (w0, h0):
            return self
        rx, ry = w1 / w0, h1 / h0
        if abs(rx - ry) > 0.01 * max(rx, ry):
            raise WarpError(
                f"photo is {w1}x{h1} but the camera was calibrated at {w0}x{h0} "
                "(different aspect ratio: cropped stream?); recalibrate at this resolution."
            )
        K = self.K.copy()
        K[0, 0] *= rx
        K[0, 1] *= rx
        K[1, 1] *= ry
        K[0, 2] = (K[0, 2] + 0.5) * rx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * ry - 0.5
        return replace(self, K=K, image_size=(w1, h1))

    # ------------------------------------------------------------------- I/O
    def to_dict(self) -> dict:
        d: dict = {
            "format": "layerwatch-camera/1",
            "created": self.created,
            "image_size": list(self.image_size),
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "approximate": bool(self.approximate),
            "marker_kind": self.marker_kind,
            "errors": {k: float(v) for k, v in self.errors.items()},
        }
        if self.rvec is not None:
            d["rvec"] = self.rvec.tolist()
        if self.tvec is not None:
            d["tvec"] = self.tvec.tolist()
        if self.markers_mm is not None:
            d["markers_mm"] = self.markers_mm.tolist()
        if self.bed_photo:
            d["bed_photo"] = str(self.bed_photo)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> CameraModel:
        try:
            return cls(
                K=d["K"],
                dist=d.get("dist", [0, 0, 0, 0, 0]),
                image_size=tuple(d["image_size"]),
                rvec=d.get("rvec"),
                tvec=d.get("tvec"),
                markers_mm=d.get("markers_mm"),
                marker_kind=d.get("marker_kind", "dots"),
                approximate=bool(d.get("approximate", False)),
                errors=dict(d.get("errors", {})),
                created=str(d.get("created", "")),
                bed_photo=str(d["bed_photo"]) if d.get("bed_photo") else None,
            )
        except KeyError as exc:
            raise ConfigError(f"camera model is missing the field {exc}; recalibrate.") from None

    def save(self, path: str | Path) -> Path:
        """Write the model as TOML (``.toml``) or JSON (anything else)."""
        path = Path(path)
        d = self.to_dict()
        if self.bed_photo:  # relative to the model's folder when it lies there (the folder can move)
            bed = Path(self.bed_photo).resolve()
            folder = path.resolve().parent
            d["bed_photo"] = str(bed.relative_to(folder)) if bed.is_relative_to(folder) else str(bed)
        if path.suffix.lower() == ".toml":
            path.write_text(tomli_w.dumps(d))
        else:
            path.write_text(json.dumps(d, indent=2))
        return path

    @classmethod
    def load(cls, path: str | Path) -> CameraModel:
        """Read a model written by :meth:`save`; errors name the file and the fix."""
        path = Path(path)
        if not path.is_file():
            raise ConfigError(
                f"camera model {path} not found: run `layerwatch calibrate` to create it."
            )
        text = path.read_text(errors="replace")
        try:
            if path.suffix.lower() == ".toml":
                d = tomllib.loads(text)
            else:
                d = json.loads(text)
        except Exception as exc:  # noqa: BLE001 - any parse error is the user's file
            raise ConfigError(f"camera model {path} is not valid: {exc}; recalibrate.") from None
        if not isinstance(d, dict):
            raise ConfigError(f"camera model {path} is not a table; recalibrate.")
        model = cls.from_dict(d)
        if model.bed_photo:
            model.bed_photo = str((path.parent / model.bed_photo).resolve())
        return model
