"""A toolpath's reading next to the file's own statements (what ``gcode info`` shows)."""

from __future__ import annotations

import math

import numpy as np

from layerwatch.gcode.statements import Disagreement, Statements, compare
from layerwatch.gcode.toolpath import FEATURES, Toolpath

__all__ = ["reading", "disagreements", "info_dict"]


def _r(v: float, nd: int = 3) -> float | None:
    return round(float(v), nd) if v is not None and math.isfinite(v) else None


def reading(tp: Toolpath) -> dict:
    """What the reader found, in the units the statements use (mm, cm³, layers)."""
    zs = [lay.z for lay in tp.layers]
    heights = sorted(lay.height for lay in tp.layers)
    area = tp.filament_area_mm2
    counts = np.bincount(tp.feature, minlength=len(FEATURES)) if tp.n_segments else np.zeros(0, np.int64)
    feats = {FEATURES[c]: int(counts[c]) for c in np.flatnonzero(counts).tolist()}
    return {
        "generator": tp.generator.describe() if tp.generator else (tp.slicer or None),
        "layers": tp.n_layers,
        "detection": tp.detection,
        "z_range_mm": [_r(min(zs)), _r(max(zs))] if zs else None,
        "first_layer_z_mm": _r(zs[0]) if zs else None,
        "median_layer_height_mm": _r(heights[len(heights) // 2]) if heights else None,
        "segments": tp.n_segments,
        "filament_commanded_mm": _r(tp.filament_commanded_mm, 2),
        "filament_commanded_cm3": _r(tp.filament_commanded_mm * area / 1000.0, 3),
        "filament_on_part_mm": _r(tp.extrusion_mm, 2),
        "filament_fed_mm": _r(tp.filament_fed_mm, 2),
        "filament_fed_cm3": _r(tp.filament_fed_mm * area / 1000.0, 3),
        "filament_diameter_mm": tp.filament_diameter,
        "volumetric_e": tp.volumetric,
        "first_layer_box_mm": [_r(v, 2) for v in tp.layers[0].bounds] if tp.layers else None,
        "part_bounds_mm": [_r(v, 2) for v in tp.bounds],
        "features": feats,
    }


def disagreements(tp: Toolpath, st: Statements | None = None) -> list[Disagreement]:
    """Where the reading contradicts the file's statements (beyond 1 layer, 2 %, 0.05 mm, 2 mm)."""
    st = st if st is not None else tp.statements
    if st is None or not tp.layers:
        return []
    return compare(
        st, layers=tp.n_layers, filament_mm=tp.filament_commanded_mm, max_z=tp.layers[-1].z,
        first_layer_box=tp.layers[0].bounds, first_layer_z=tp.layers[0].z,
        filament_cm3=tp.filament_commanded_mm * tp.filament_area_mm2 / 1000.0,
    )


def info_dict(tp: Toolpath) -> dict:
    """JSON-ready: ``reading``, ``statements``, ``disagreements`` (text) and ``warnings``."""
    return {
        "file": tp.source,
        "reading": reading(tp),
        "statements": tp.statements.as_dict() if tp.statements else None,
        "disagreements": [str(d) for d in disagreements(tp)],
        "warnings": list(tp.warnings),
    }
