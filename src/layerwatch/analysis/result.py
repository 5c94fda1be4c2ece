"""The result of analysing one layer, as passed to policy, storage and UI.

References
----------
Petsiuk & Pearce (2022), eq. (5): ``a% = S_A / S_P``, the anomalous area
over the printed area.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

__all__ = ["Region", "LayerResult"]


@dataclass
class Region:
    """A connected group of anomalous blocks.

    Attributes
    ----------
    area_mm2 : float
        Area of the region on the layer plane, mm^2.
    bbox_mm : tuple of float
        ``(xmin, ymin, xmax, ymax)`` in bed mm.
    centroid_mm : tuple of float
        ``(x, y)`` in bed mm.
    n_blocks : int
        Number of HOG blocks in the region.
    mean_similarity : float
        Mean similarity of its blocks, in [0, 1].
    min_similarity : float
        Lowest similarity of its blocks, in [0, 1].
    outside_fraction : float
        Share of the region outside the layer's footprint (material where
        none should be: spaghetti, detachment, foreign body), in [0, 1].
    """

    area_mm2: float
    bbox_mm: tuple[float, float, float, float]
    centroid_mm: tuple[float, float]
    n_blocks: int
    mean_similarity: float
    min_similarity: float = 0.0
    outside_fraction: float = 0.0


def _clean(value: Any) -> Any:
    """Make a value JSON-safe (numpy scalars/arrays, NaN -> None)."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclass
class LayerResult:
    """Everything known about one analysed layer.

    Attributes
    ----------
    layer : int
        0-based layer index.
    z : float
        Layer top height, mm.
    status : str
        ``"ok"`` (analysed), ``"skipped"`` (nothing to analyse, e.g. empty
        layer) or ``"error"`` (photo/warp failed; ``message`` says why).
    metric : str
        Similarity measure used, e.g. ``"cosine"``.
    threshold : float
        Block threshold ``T_S`` in [0, 1] (paper: 0.7).
    anomaly_ratio : float
        ``a%`` of eq. (5) as a fraction in [0, 1] (0 when nothing is printed).
    printed_area_mm2 : float
        ``S_P``, printed (footprint) area considered, mm^2.
    anomalous_area_mm2 : float
        ``S_A``, anomalous area, mm^2.
    outside_area_mm2 : float
        Part of ``anomalous_area_mm2`` outside the layer's (undilated)
        footprint, i.e. in the margin band around the part, mm^2.
    n_blocks, n_anomalous : int
        Blocks considered and blocks below threshold.
    regions : list of Region
        Connected failing regions, largest first.
    heatmap : ndarray, shape (N, M), float32, or None
        Similarity per block in [0, 1]; not written to JSON unless asked.
    mask : ndarray, shape (N, M), bool, or None
        Blocks that were considered (footprint plus margin, seen by the
        camera); written to JSON together with the heatmap.
    timings_ms : dict
        Stage timings in milliseconds (``"warp"``, ``"render"``, ``"hog"``...).
    images : dict
        Paths of stored pictures (``"photo"``, ``"top"``, ``"reference"``,
        ``"overlay"``) relative to the results folder.
    message : str
        Human-readable note (error reason for ``status == "error"``).
    extra : dict
        Free-form additional values (per-metric scores, pose drift...).
    """

    layer: int
    z: float
    status: str = "ok"
    metric: str = "cosine"
    threshold: float = 0.7
    anomaly_ratio: float = 0.0
    printed_area_mm2: float = 0.0
    anomalous_area_mm2: float = 0.0
    outside_area_mm2: float = 0.0
    n_blocks: int = 0
    n_anomalous: int = 0
    regions: list[Region] = field(default_factory=list)
    heatmap: np.ndarray | None = None
    mask: np.ndarray | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    images: dict[str, str] = field(default_factory=dict)
    message: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_dict(self, include_heatmap: bool = False) -> dict[str, Any]:
        d = asdict(self)
        d.pop("heatmap")
        d.pop("mask")
        if include_heatmap and self.heatmap is not None:
            d["heatmap"] = np.round(np.asarray(self.heatmap, dtype=np.float64), 4).tolist()
        if include_heatmap and self.mask is not None:
            d["mask"] = np.asarray(self.mask, dtype=np.uint8).tolist()
        return _clean(d)

    def to_json(self, include_heatmap: bool = False, **kwargs: Any) -> str:
        return json.dumps(self.to_dict(include_heatmap=include_heatmap), **kwargs)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LayerResult:
        d = dict(d)
        regions = [
            Region(
                area_mm2=float(r["area_mm2"]),
                bbox_mm=tuple(r["bbox_mm"]),
                centroid_mm=tuple(r["centroid_mm"]),
                n_blocks=int(r["n_blocks"]),
                mean_similarity=float(r["mean_similarity"]),
                min_similarity=float(r.get("min_similarity", 0.0)),
                outside_fraction=float(r.get("outside_fraction", 0.0)),
            )
            for r in d.pop("regions", [])
        ]
        heat = d.pop("heatmap", None)
        mask = d.pop("mask", None)
        known = {f for f in cls.__dataclass_fields__}
        kwargs = {k: v for k, v in d.items() if k in known}
        for key in ("anomaly_ratio", "printed_area_mm2", "anomalous_area_mm2", "outside_area_mm2"):
            if kwargs.get(key) is None and key in kwargs:
                kwargs[key] = float("nan")
        res = cls(**kwargs, regions=regions)
        if heat is not None:
            res.heatmap = np.asarray(heat, dtype=np.float32)
        if mask is not None:
            res.mask = np.asarray(mask, dtype=bool)
        return res

    @classmethod
    def from_json(cls, text: str) -> LayerResult:
        return cls.from_dict(json.loads(text))
