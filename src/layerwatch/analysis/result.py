"""The typed per-layer record: one :class:`LayerResult` shared by the pipeline, policy, storage, web and reports.

The comparison (:func:`~layerwatch.analysis.scoring.analyze_layer`) fills it
first, so it is defined here, below :mod:`layerwatch.pipeline`, which
re-exports it; the per-layer step adds timings, the policy its decision, the
monitor its latencies. Every value has a typed field (no free-form dict).

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

__all__ = ["BlockGrid", "LayerChangeStats", "LayerResult", "MetricScore", "Region", "SceneStats"]


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
    kind : str
        What failed there, one of
        :data:`~layerwatch.analysis.failure_kinds.FAILURE_KINDS`; ``""``
        when the region was not typed.
    kind_confidence : float
        Confidence of ``kind``, in [0, 1] (0 when not typed).
    displacement_mm : tuple of float or None
        ``(dx, dy)`` in bed mm for a layer shift or a moved/detached part
        (registration of the printed part against the reference); ``None``
        otherwise.
    outline_mm : tuple of polygons
        The area the region shows the operator when it is not its blocks, as
        polygons of ``(x, y)`` bed mm: for a layer shift or a moved/detached
        part, where the layer is and should not be and where it should be and
        is not (:mod:`~layerwatch.analysis.region_outline`); for a foreign
        body, its own pixels in the region's box when they stand out from
        both the bed and the part; ``()`` otherwise.
    """

    area_mm2: float
    bbox_mm: tuple[float, float, float, float]
    centroid_mm: tuple[float, float]
    n_blocks: int
    mean_similarity: float
    min_similarity: float = 0.0
    outside_fraction: float = 0.0
    kind: str = ""
    kind_confidence: float = 0.0
    displacement_mm: tuple[float, float] | None = None
    outline_mm: tuple[tuple[tuple[float, float], ...], ...] = ()


@dataclass
class BlockGrid:
    """The analysis grid a result was computed on (see :func:`~layerwatch.analysis.scoring.block_geometry`).

    Attributes
    ----------
    cell_px, block_cells, min_region_blocks : int
        HOG cell side (px), block side (cells), smallest kept region (blocks).
    cell_mm, block_mm, stride_mm : float
        Cell side, block side (the analysis window) and block stride, mm.
    tile_area_mm2 : float
        Area one block stands for, mm^2.
    paper_block_mm : float
        The paper's block-size figure (twice ``block_mm``).
    """

    cell_px: int = 8
    block_cells: int = 2
    min_region_blocks: int = 1
    cell_mm: float = 0.0
    block_mm: float = 0.0
    stride_mm: float = 0.0
    tile_area_mm2: float = 0.0
    paper_block_mm: float = 0.0


@dataclass
class MetricScore:
    """One measure of Table 2 on a layer's blocks (``LayerResult.per_metric``), at the result's threshold.

    Attributes
    ----------
    anomaly_ratio : float
        a% (eq. 5) in [0, 1], before the ``min_region_blocks`` filter.
    n_anomalous : int
    mean_similarity : float
        Over the considered blocks, in [0, 1].
    """

    anomaly_ratio: float
    n_anomalous: int
    mean_similarity: float


@dataclass
class SceneStats:
    """What the scene channel saw in one photo (``LayerResult.scene``; :mod:`layerwatch.pipeline.scene`).

    Attributes
    ----------
    baseline : str
        What the expected appearance started from: ``"bed photo"``,
        ``"first photo"``, or ``""`` when this photo became the baseline
        (nothing to compare with yet).
    threshold : float
        The frame's block threshold, grey levels (mean absolute residual).
    noise : float
        Robust spread of the frame's block scores (1.4826 MAD), grey levels.
    blocks_scored, blocks_changed : int
        Working-image blocks compared and found changed outside the predicted change.
    gain : tuple of float
        Photometric gain per channel (BGR) of the photo against the expected appearance.
    ms : float
        Time of the channel on this photo, ms.
    """

    baseline: str = ""
    threshold: float = 0.0
    noise: float = 0.0
    blocks_scored: int = 0
    blocks_changed: int = 0
    gain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ms: float = 0.0


@dataclass
class LayerChangeStats:
    """What the "changed as predicted" channel saw in one photo (``LayerResult.layer_change``; :mod:`layerwatch.analysis.layer_change`).

    Attributes
    ----------
    judged : bool
        Whether the photo pair could be judged (a previous photo of the print,
        texture to calibrate the noise on); ``note`` says why not.
    previous_layer : int
        Layer of the previous photo compared with (-1: none).
    px_judged, px_unchanged : int
        Footprint pixels (working image) whose window has texture above the noise
        that the parallax changes, and of those the ones that look as in the previous photo.
    unchanged_mm2 : float
        Area of the failing regions it reported, mm^2 on the layer's plane.
    added_mm2 : float
        What those regions added to ``S_A`` (eq. 5): their area not already
        under an anomalous HOG block, mm^2.
    noise : float
        Noise variance of one photo's high-passed texture, grey levels^2.
    parallax_px : float
        Image shift of the height printed since the previous photo, working px.
    note : str
        Why the pair was not judged (``""`` when it was).
    """

    judged: bool = False
    previous_layer: int = -1
    px_judged: int = 0
    px_unchanged: int = 0
    unchanged_mm2: float = 0.0
    added_mm2: float = 0.0
    noise: float = 0.0
    parallax_px: float = 0.0
    note: str = ""


def _region(r: dict[str, Any]) -> Region:
    return Region(
        area_mm2=float(r["area_mm2"]),
        bbox_mm=tuple(r["bbox_mm"]),
        centroid_mm=tuple(r["centroid_mm"]),
        n_blocks=int(r["n_blocks"]),
        mean_similarity=float(r["mean_similarity"]),
        min_similarity=float(r.get("min_similarity", 0.0)),
        outside_fraction=float(r.get("outside_fraction", 0.0)),
        kind=str(r.get("kind") or ""),
        kind_confidence=float(r.get("kind_confidence") or 0.0),
        displacement_mm=None if r.get("displacement_mm") is None else (
            float(r["displacement_mm"][0]), float(r["displacement_mm"][1])),
        outline_mm=tuple(tuple((float(x), float(y)) for x, y in poly) for poly in r.get("outline_mm") or ()),
    )


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
        ``S_A``, anomalous area, mm^2: the anomalous blocks' tiles, or with
        ``[analysis] anomalous_area = "printed"`` the part's share of each
        (:func:`~layerwatch.analysis.scoring.printed_weight`).
    outside_area_mm2 : float
        Area of the anomalous blocks' tiles outside the layer's (undilated)
        footprint, i.e. beside the part or in the margin band around it, mm^2
        (part of ``anomalous_area_mm2`` only when whole tiles are counted).
    uncounted_mm2 : float
        Area of the anomalous blocks' tiles that ``anomalous_area_mm2`` leaves
        out, mm^2: with ``anomalous_area = "printed"`` (or ``"part"``) their
        share beside the part; 0 with whole tiles. ``anomalous_area_mm2 +
        uncounted_mm2`` is the image area that shows the anomaly, whatever
        S_A counts of it: the policy's minimum-area test
        (:func:`~layerwatch.pipeline.policy.layer_alarm`) asks it, a% does not.
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
    grid : BlockGrid or None
        The block grid of the comparison.
    similarity_mean, similarity_min : float
        Mean and lowest similarity of the considered blocks (1 when none).
    shown_blocks : list of int or None
        Flat (N, M) indices of the blocks the overlay draws when hysteresis
        grew the failing regions (``grow_threshold > 0``); ``None`` otherwise
        (the anomalous blocks are drawn).
    per_metric : dict of str to MetricScore
        All twelve measures (only when asked: ``all_metrics``).
    decision, decision_reason : str
        The pause policy's action after this layer (``"none"``, ``"notify"``,
        ``"pause"``, ``"cancel"``) and why; ``""`` before it was judged.
    photo_ms : float or None
        Monitor: printer trigger to photo, ms.
    trigger_to_pause_ms : float or None
        Monitor: printer trigger to the pause request, ms (layers that paused).
    simulated_failures : list of str
        Simulator: failure types injected in the photo (the demo).
    frame_quality : dict of str to float
        Camera-fault gate: the figures of a refused frame (``status="camera_fault"``;
        :func:`~layerwatch.analysis.frame_quality.assess_frame`).
    outside_anomalous_mm2 : float
        Scene channel: area changed beside the layer's predicted change (not
        in a%, which stays eq. 5 over the printed area), mm^2 on the layer
        plane; 0 when the channel is off or had no baseline.
    outside_regions : list of Region
        Scene channel: the connected changed areas (bed mm), largest first.
    scene : SceneStats or None
        Scene channel's figures for this photo; ``None`` when it is off.
    failed_check : str
        The check that failed on this photo (:mod:`layerwatch.pipeline.checks`):
        ``"empty_bed"`` (job start, ``layer`` -1), ``"first_layer"`` or
        ``"nothing_extruded"``; ``""`` when none failed. The pause policy
        acts on it at once.
    check_regions : list of Region
        What the checks found (bed mm), each with its ``kind``.
    view_shift_px : (int, int)
        Residual shift of the photo's top view against the reference that was
        undone before the comparison, top-view px (``[analysis] register_mm``,
        :mod:`layerwatch.analysis.view_shift`); ``(0, 0)`` when none.
    """

    layer: int
    z: float
    status: str = "ok"
    metric: str = "cosine"
    threshold: float = 0.7
    anomaly_ratio: float = 0.0
    printed_area_mm2: float = 0.0
    anomalous_area_mm2: float = 0.0
    uncounted_mm2: float = 0.0
    outside_area_mm2: float = 0.0
    n_blocks: int = 0
    n_anomalous: int = 0
    regions: list[Region] = field(default_factory=list)
    heatmap: np.ndarray | None = None
    mask: np.ndarray | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    images: dict[str, str] = field(default_factory=dict)
    message: str = ""
    grid: BlockGrid | None = None
    similarity_mean: float = 1.0
    similarity_min: float = 1.0
    shown_blocks: list[int] | None = None
    per_metric: dict[str, MetricScore] = field(default_factory=dict)
    decision: str = ""
    decision_reason: str = ""
    photo_ms: float | None = None
    trigger_to_pause_ms: float | None = None
    simulated_failures: list[str] = field(default_factory=list)
    frame_quality: dict[str, float] = field(default_factory=dict)
    outside_anomalous_mm2: float = 0.0
    outside_regions: list[Region] = field(default_factory=list)
    scene: SceneStats | None = None
    failed_check: str = ""
    check_regions: list[Region] = field(default_factory=list)
    view_shift_px: tuple[int, int] = (0, 0)
    layer_change: LayerChangeStats | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def region_blocks(self) -> int:
        """Blocks the overlay draws: ``shown_blocks`` when grown, else the anomalous blocks."""
        return self.n_anomalous if self.shown_blocks is None else len(self.shown_blocks)

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
        regions = [_region(r) for r in d.pop("regions", [])]
        d["outside_regions"] = [_region(r) for r in d.get("outside_regions") or []]
        d["check_regions"] = [_region(r) for r in d.get("check_regions") or []]
        if isinstance(d.get("scene"), dict):
            sc = d["scene"]
            fields: dict[str, Any] = {k: v for k, v in sc.items() if k in SceneStats.__dataclass_fields__}
            if "gain" in fields:
                fields["gain"] = tuple(fields["gain"])
            d["scene"] = SceneStats(**fields)
        if d.get("view_shift_px") is not None:
            d["view_shift_px"] = tuple(int(v) for v in d["view_shift_px"])
        if isinstance(d.get("layer_change"), dict):
            d["layer_change"] = LayerChangeStats(**{k: v for k, v in d["layer_change"].items()
                                                    if k in LayerChangeStats.__dataclass_fields__})
        heat = d.pop("heatmap", None)
        mask = d.pop("mask", None)
        for key, value in (d.pop("extra", None) or {}).items():  # rows written before the typed fields
            d.setdefault(key, value)
        if isinstance(d.get("grid"), dict):
            d["grid"] = BlockGrid(**{k: v for k, v in d["grid"].items() if k in BlockGrid.__dataclass_fields__})
        if isinstance(d.get("per_metric"), dict):
            d["per_metric"] = {name: MetricScore(**v) for name, v in d["per_metric"].items()}
        known = {f for f in cls.__dataclass_fields__}
        kwargs = {k: v for k, v in d.items() if k in known}
        for key in ("anomaly_ratio", "printed_area_mm2", "anomalous_area_mm2", "outside_area_mm2",
                    "outside_anomalous_mm2"):
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
