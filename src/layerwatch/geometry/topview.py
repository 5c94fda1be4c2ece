"""The virtual top view: a fixed-scale orthographic image of one bed plane.

Frame convention (see ``DESIGN.md``): the top view shows an axis-aligned
rectangle of the bed (the *observed square*, 90 x 90 mm by default) at
``px_per_mm`` pixels per millimetre (6.67 in the paper). The image centre is
the centre of the observed square and bed +Y points up in the image.

Pixel coordinates follow OpenCV: the centre of pixel ``(row, col)`` is at
``(u, v) = (col, row)``; the observed square spans ``u`` in
``[-0.5, W - 0.5]``. Therefore::

    u = (x - cx) * s + (W - 1) / 2
    v = (H - 1) / 2 - (y - cy) * s

References
----------
Petsiuk & Pearce (2022), Section 2.3, eqs. (1)-(3): the top view is the
image of the layer plane under a virtual orthographic camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from layerwatch.errors import ConfigError

__all__ = ["TopView"]


@dataclass(frozen=True)
class TopView:
    """Geometry of the virtual top-view image.

    Parameters
    ----------
    px_per_mm : float
        Scale ``s`` in pixels per millimetre (paper: 6.67).
    width_mm, height_mm : float
        Size of the observed rectangle on the bed, mm (paper: 90 x 90).
    center_mm : tuple of float
        Bed coordinates ``(cx, cy)`` of the rectangle's centre, mm.
    """

    px_per_mm: float = 6.67
    width_mm: float = 90.0
    height_mm: float = 90.0
    center_mm: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (self.px_per_mm > 0 and np.isfinite(self.px_per_mm)):
            raise ConfigError(f"top view px_per_mm must be > 0, got {self.px_per_mm}.")
        if not (self.width_mm > 0 and self.height_mm > 0):
            raise ConfigError(
                f"observed area must be positive, got {self.width_mm} x {self.height_mm} mm."
            )
        w, h = self.shape[1], self.shape[0]
        if w * h > 64_000_000:
            raise ConfigError(
                f"top view of {w}x{h} px is too large; lower px_per_mm or the observed area."
            )

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(H, W)`` in pixels (600 x 600 for the defaults)."""
        return (
            int(round(self.height_mm * self.px_per_mm)),
            int(round(self.width_mm * self.px_per_mm)),
        )

    @property
    def top_from_bed(self) -> np.ndarray:
        """Affine map, shape (3, 3), bed mm ``(x, y, 1)`` -> top-view px ``(u, v, 1)``."""
        h, w = self.shape
        s = self.px_per_mm
        cx, cy = self.center_mm
        return np.array(
            [
                [s, 0.0, (w - 1) / 2.0 - s * cx],
                [0.0, -s, (h - 1) / 2.0 + s * cy],
                [0.0, 0.0, 1.0],
            ]
        )

    @property
    def bed_from_top(self) -> np.ndarray:
        """Inverse of :attr:`top_from_bed`, shape (3, 3)."""
        return np.linalg.inv(self.top_from_bed)

    def to_px(self, xy_mm: np.ndarray) -> np.ndarray:
        """Map bed points to top-view pixel coordinates.

        Parameters
        ----------
        xy_mm : ndarray, shape (..., 2)
            Bed coordinates in mm.

        Returns
        -------
        ndarray, shape (..., 2), float64
            ``(u, v)`` pixel coordinates (OpenCV convention).
        """
        xy = np.asarray(xy_mm, dtype=np.float64)
        h, w = self.shape
        s = self.px_per_mm
        u = (xy[..., 0] - self.center_mm[0]) * s + (w - 1) / 2.0
        v = (h - 1) / 2.0 - (xy[..., 1] - self.center_mm[1]) * s
        return np.stack([u, v], axis=-1)

    def to_mm(self, uv_px: np.ndarray) -> np.ndarray:
        """Map top-view pixel coordinates ``(u, v)`` (..., 2) to bed mm (..., 2)."""
        uv = np.asarray(uv_px, dtype=np.float64)
        h, w = self.shape
        s = self.px_per_mm
        x = (uv[..., 0] - (w - 1) / 2.0) / s + self.center_mm[0]
        y = ((h - 1) / 2.0 - uv[..., 1]) / s + self.center_mm[1]
        return np.stack([x, y], axis=-1)

    @property
    def corners_mm(self) -> np.ndarray:
        """Corners of the observed rectangle in bed mm, shape (4, 2).

        Order: (-x, -y), (+x, -y), (+x, +y), (-x, +y) — counter-clockwise seen
        from above, starting at the front-left corner.
        """
        cx, cy = self.center_mm
        hx, hy = self.width_mm / 2.0, self.height_mm / 2.0
        return np.array(
            [[cx - hx, cy - hy], [cx + hx, cy - hy], [cx + hx, cy + hy], [cx - hx, cy + hy]]
        )

    def to_dict(self) -> dict:
        return {
            "px_per_mm": self.px_per_mm,
            "width_mm": self.width_mm,
            "height_mm": self.height_mm,
            "center_mm": list(self.center_mm),
        }

    @classmethod
    def from_dict(cls, d: dict) -> TopView:
        cx, cy = (float(v) for v in d.get("center_mm", (0.0, 0.0)))
        return cls(
            px_per_mm=float(d.get("px_per_mm", 6.67)),
            width_mm=float(d.get("width_mm", 90.0)),
            height_mm=float(d.get("height_mm", 90.0)),
            center_mm=(cx, cy),
        )
