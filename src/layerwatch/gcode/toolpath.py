"""Per-layer toolpaths: the parsed form of a G-code file.

A :class:`Toolpath` stores every *extruding* segment of a print in flat
NumPy arrays ordered as in the file, and a tuple of :class:`Layer` records
that slice those arrays. Travel moves are not kept (they leave no material);
their count is in the layer metadata.

Units: millimetres for positions, widths and heights; millimetres of
filament for ``e``. Bed frame: the G-code's own origin, +Z up.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from layerwatch.gcode.generators import Generator
from layerwatch.gcode.statements import Statements

__all__ = ["FEATURES", "NOT_PART", "Layer", "Toolpath", "feature_code", "part_mask"]

#: Feature types a slicer may name; the index is the code stored in ``Toolpath.feature``.
FEATURES: tuple[str, ...] = (
    "unknown",
    "perimeter",
    "external_perimeter",
    "infill",
    "solid_infill",
    "top_solid_infill",
    "bridge",
    "support",
    "skirt",
    "wipe",
    "other",
    "purge",
    "brim",
    "wipe_tower",
)
#: features that are not the part: its bounds and footprint leave them out (references still draw them)
NOT_PART: tuple[str, ...] = ("skirt", "purge", "brim", "wipe_tower")


def feature_code(name: str) -> int:
    """Code of a feature name in :data:`FEATURES` (``0`` = unknown)."""
    try:
        return FEATURES.index(name)
    except ValueError:
        return 0


_IS_PART = np.ones(256, bool)
_IS_PART[[FEATURES.index(f) for f in NOT_PART]] = False


def part_mask(feature: np.ndarray) -> np.ndarray:
    """True for segments of the part itself (not skirt, brim, purge line or wipe tower), shape (S,)."""
    return _IS_PART[np.asarray(feature, np.uint8)]


@dataclass(frozen=True)
class Layer:
    """Metadata of one layer.

    Attributes
    ----------
    index : int
        0-based layer number in print order.
    z : float
        Height of the layer's top surface (the nozzle Z while printing it), mm.
    height : float
        Layer thickness, mm (``z`` minus the previous layer's ``z``; the
        first layer's ``z``).
    seg_start, seg_stop : int
        Slice ``[seg_start, seg_stop)`` into the :class:`Toolpath` arrays.
    line_start, line_stop : int
        1-based source line range ``[line_start, line_stop)`` of the layer.
    bounds : tuple of float
        ``(xmin, ymin, xmax, ymax)`` of the part's extruding segments (skirt,
        brim, purge lines and wipe tower left out; all segments when the layer
        has nothing else), mm; NaN when the layer has no extrusion.
    extrusion_mm : float
        Filament length extruded in this layer, mm.
    n_travel : int
        Number of travel (non-extruding XY) moves in the layer.
    """

    index: int
    z: float
    height: float
    seg_start: int
    seg_stop: int
    line_start: int
    line_stop: int
    bounds: tuple[float, float, float, float]
    extrusion_mm: float
    n_travel: int = 0

    @property
    def n_segments(self) -> int:
        return self.seg_stop - self.seg_start


def _synthetic_layers(
    start: np.ndarray, end: np.ndarray, e: np.ndarray, layer_z: np.ndarray, heights: np.ndarray,
    bounds_idx: np.ndarray,
) -> tuple[Layer, ...]:
    """The layers of :meth:`Toolpath.from_segments`: layer ``i`` holds segments
    ``bounds_idx[i]:bounds_idx[i + 1]`` at ``layer_z[i]`` (mm), ``heights[i]`` thick (mm), with
    its bounding box (mm) and filament used (``e``, mm)."""
    layers = []
    for i in range(len(bounds_idx) - 1):
        a, b = int(bounds_idx[i]), int(bounds_idx[i + 1])
        pts = np.concatenate([start[a:b], end[a:b]])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        layers.append(
            Layer(
                index=i,
                z=float(layer_z[i]),
                height=float(heights[i]),
                seg_start=a,
                seg_stop=b,
                line_start=0,
                line_stop=0,
                bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
                extrusion_mm=float(e[a:b].sum()),
            )
        )
    return tuple(layers)


@dataclass
class Toolpath:
    """Extruding segments of a whole print plus per-layer metadata.

    Attributes
    ----------
    start, end : ndarray, shape (S, 2), float64
        Segment endpoints ``(x, y)`` in bed mm.
    z : ndarray, shape (S,), float64
        Nozzle Z of each segment, mm.
    e : ndarray, shape (S,), float64
        Filament extruded along the segment, mm (> 0).
    width : ndarray, shape (S,), float32
        Estimated bead width, mm, from ``e``, filament diameter and layer
        height (rounded-rectangle bead cross-section).
    feature : ndarray, shape (S,), uint8
        Feature code, index into :data:`FEATURES`.
    tool : ndarray, shape (S,), uint8
        Active tool (extruder) index.
    line : ndarray, shape (S,), int64
        1-based source line of the move.
    layers : tuple of Layer
        Layers in print order; their segment slices tile ``[0, S)``.
    detection : str
        How layers were found, e.g. ``"tags:prusaslicer"``, ``"z"`` or
        ``"spiral"``.
    filament_diameter : float
        Filament diameter used for widths, mm.
    source : str
        File name or description of the input.
    slicer : str or None
        Slicer named in the file header, if any.
    warnings : list of str
        Non-fatal problems found while parsing (``file:line: text``).
    generator : Generator or None
        Program that wrote the file (name, version, header line).
    statements : Statements or None
        What the file states about itself (layer count, filament, boxes).
    filament_commanded_mm : float
        Filament the E words of extruding XY moves ask for, mm (what slicers
        state as "filament used"; M221 not applied).
    filament_fed_mm : float
        Filament the printer feeds over the whole file, mm: the high-water
        mark of the cumulative E with M221 applied, so flushes and primes
        (E-only moves) count and retract/unretract pairs count once.
    filament_area_mm2 : float
        Filament cross-section, mm² (volume = length x area).
    volumetric : bool
        The file's E words are volumes (UltiGCode, ``M200 D``), converted to lengths.
    """

    start: np.ndarray
    end: np.ndarray
    z: np.ndarray
    e: np.ndarray
    width: np.ndarray
    feature: np.ndarray
    tool: np.ndarray
    line: np.ndarray
    layers: tuple[Layer, ...]
    detection: str = "z"
    filament_diameter: float = 1.75
    source: str = "<memory>"
    slicer: str | None = None
    warnings: list[str] = field(default_factory=list)
    generator: Generator | None = None
    statements: Statements | None = None
    filament_commanded_mm: float = float("nan")
    filament_fed_mm: float = float("nan")
    volumetric: bool = False

    @property
    def filament_area_mm2(self) -> float:
        return float(np.pi * self.filament_diameter**2 / 4.0)

    @property
    def n_layers(self) -> int:
        return len(self.layers)

    @property
    def n_segments(self) -> int:
        return int(self.start.shape[0])

    def layer_slice(self, index: int) -> slice:
        """Segment slice of layer ``index``."""
        layer = self.layers[index]
        return slice(layer.seg_start, layer.seg_stop)

    def up_to(self, index: int) -> slice:
        """Segment slice of layers ``0..index`` inclusive (what is printed after ``index``)."""
        return slice(0, self.layers[index].seg_stop)

    def layer_index_at(self, z: float, tol: float = 1e-3) -> int:
        """Index of the layer whose top is at ``z`` (nearest within ``tol`` mm), or -1."""
        if not self.layers:
            return -1
        zs = np.array([lay.z for lay in self.layers])
        i = int(np.argmin(np.abs(zs - z)))
        return i if abs(zs[i] - z) <= tol else -1

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the part's extrusion (skirt, brim, purge, wipe tower
        left out unless nothing else is there), mm (NaN if none)."""
        if self.n_segments == 0:
            return (float("nan"),) * 4
        keep = part_mask(self.feature)
        if not keep.any():
            keep[:] = True
        # column by column with a mask (no copies): NumPy reduces a strided column ~10x faster
        # than an (S, 2) array along axis 0
        a, b = self.start, self.end
        lo = [float(np.minimum(a[:, k].min(where=keep, initial=np.inf), b[:, k].min(where=keep, initial=np.inf)))
              for k in (0, 1)]
        hi = [float(np.maximum(a[:, k].max(where=keep, initial=-np.inf), b[:, k].max(where=keep, initial=-np.inf)))
              for k in (0, 1)]
        return (lo[0], lo[1], hi[0], hi[1])

    @property
    def extrusion_mm(self) -> float:
        return float(self.e.sum())

    def nbytes(self) -> int:
        """Memory held by the segment arrays, bytes."""
        arrays = (self.start, self.end, self.z, self.e, self.width, self.feature, self.tool, self.line)
        return int(sum(a.nbytes for a in arrays))

    @classmethod
    def from_segments(
        cls,
        start: np.ndarray,
        end: np.ndarray,
        z: np.ndarray,
        width: np.ndarray | float = 0.45,
        e: np.ndarray | None = None,
        feature: np.ndarray | None = None,
        layer_height: float | None = None,
        source: str = "<synthetic>",
    ) -> Toolpath:
        """Build a toolpath from raw segments, grouping layers by equal ``z``.

        Useful for tests and synthetic parts. Segments must be ordered by
        non-decreasing ``z``.

        Parameters
        ----------
        start, end : array_like, shape (S, 2)
            Endpoints in mm.
        z : array_like, shape (S,)
            Segment heights in mm.
        width : float or array_like, shape (S,)
            Bead width in mm.
        e : array_like, shape (S,), optional
            Filament length; defaults to the volume-equivalent for 1.75 mm
            filament.
        feature : array_like of uint8, shape (S,), optional
        layer_height : float, optional
            Height of the first layer; defaults to its ``z``.
        """
        start = np.asarray(start, dtype=np.float64).reshape(-1, 2)
        end = np.asarray(end, dtype=np.float64).reshape(-1, 2)
        z = np.asarray(z, dtype=np.float64).reshape(-1)
        n = start.shape[0]
        width_arr = np.broadcast_to(np.asarray(width, dtype=np.float32), (n,)).copy()
        if np.any(np.diff(z) < -1e-9):
            raise ValueError("segments must be ordered by non-decreasing z")
        # group by z
        cuts = np.flatnonzero(np.diff(z) > 1e-6) + 1
        bounds_idx = np.concatenate([[0], cuts, [n]]).astype(int)
        layer_z = z[bounds_idx[:-1]] if n else np.array([])
        length = np.linalg.norm(end - start, axis=1)
        heights = np.diff(np.concatenate([[0.0], layer_z]))
        if layer_height is not None and len(heights):
            heights[0] = layer_height
        seg_h = np.repeat(heights, np.diff(bounds_idx)) if n else np.zeros(0)
        if e is None:
            area = np.pi * (1.75 / 2) ** 2
            bead = (width_arr - seg_h) * seg_h + np.pi * (seg_h / 2) ** 2
            e = length * bead / area
        e = np.asarray(e, dtype=np.float64).reshape(-1)
        feat = (
            np.zeros(n, np.uint8) if feature is None else np.asarray(feature, np.uint8).reshape(-1)
        )
        layers = _synthetic_layers(start, end, e, layer_z, heights, bounds_idx)
        return cls(
            start=start,
            end=end,
            z=z,
            e=e,
            width=width_arr,
            feature=feat,
            tool=np.zeros(n, np.uint8),
            line=np.zeros(n, np.int64),
            layers=layers,
            detection="synthetic",
            source=source,
        )
