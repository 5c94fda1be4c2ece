"""Pictures of a layer analysis: heatmap overlay and plain heatmap (PNG).

The overlay follows the paper's Figs. 13 and 15: the similarity heatmap is
colour-mapped (matplotlib ``RdYlGn``: red = dissimilar, green = similar)
over the grey top view where blocks were considered, failing regions are
outlined in magenta, the layer's footprint in cyan, a region's own shape
where the typer found one (a moved part's displaced bands, a foreign body's
pixels: ``Region.outline_mm``) in white, and a caption states
layer, measure, threshold and a%. :func:`write_overlay` is the one function
the CLI, reports and dashboard use to write it.

References
----------
Petsiuk & Pearce (2022), Figs. 13 and 15.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from layerwatch.analysis.block_masks import block_tiles
from layerwatch.analysis.result import BlockGrid, LayerResult
from layerwatch.analysis.scoring import grey_u8
from layerwatch.errors import AnalysisError
from layerwatch.geometry.topview import TopView

__all__ = ["overlay_image", "heatmap_image", "write_overlay", "write_png", "anomalous_blocks", "region_label"]

_CMAP = "RdYlGn"
_FOOTPRINT_RGB = (0, 220, 255)
_REGION_RGB = (255, 0, 255)
_OUTSIDE_RGB = (255, 160, 0)  # scene channel: change beside the print
_SHAPE_RGB = (255, 255, 255)  # a region's own shape (Region.outline_mm): a moved part, a foreign body


@lru_cache(maxsize=1)
def _cmap():
    """matplotlib's :data:`_CMAP`, its lookup table built once per process (the registry hands out a new copy,
    with a table to build, on every access: ~0.15 ms per overlay)."""
    from matplotlib import colormaps  # matplotlib takes ~0.3 s to import; only heatmaps need it

    cmap = colormaps[_CMAP]
    cmap(0.0)  # builds the lookup table now (read-only afterwards: the farm's threads share it)
    return cmap


def _colormap(values: np.ndarray) -> np.ndarray:
    """Map values in [0, 1] to RGB uint8 with matplotlib's colormap (no pyplot)."""
    rgba = _cmap()(np.clip(np.nan_to_num(values, nan=0.0), 0.0, 1.0), bytes=True)
    return rgba[..., :3]


def _grid(result: LayerResult) -> tuple[int, int, int]:
    grid = result.grid or BlockGrid()
    return int(grid.cell_px), int(grid.block_cells), int(grid.min_region_blocks)


def anomalous_blocks(result: LayerResult) -> np.ndarray:
    """Blocks of the failing regions in ``result``, (N, M) bool.

    The blocks the analysis drew (``result.shown_blocks``: grown by
    hysteresis when it used ``grow_threshold``), else the considered blocks
    below T_S in groups of at least ``min_region_blocks``.
    """
    heat = np.asarray(result.heatmap, dtype=np.float32)
    shown = result.shown_blocks
    if shown is not None:  # grown by the analysis (hysteresis, possibly beyond the considered blocks)
        out = np.zeros(heat.size, bool)
        out[np.asarray(shown, dtype=np.int64)] = True
        return out.reshape(heat.shape)
    mask = np.ones(heat.shape, bool) if result.mask is None else np.asarray(result.mask, bool)
    anom = mask & (heat < result.threshold)
    min_blocks = _grid(result)[2]
    if min_blocks > 1 and anom.any():
        labels, _ = ndimage.label(anom, structure=np.ones((3, 3), dtype=bool))
        anom = (np.bincount(labels.ravel()) >= min_blocks)[labels] & anom
    return anom


def _to_rgb(top: np.ndarray) -> np.ndarray:
    grey = grey_u8(top, "top view")
    return np.repeat(grey[..., None], 3, axis=2)


def _outline(img: np.ndarray, mask: np.ndarray, rgb, thickness: int) -> None:
    if not mask.any():
        return
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(img, contours, -1, tuple(int(v) for v in rgb), thickness, lineType=cv2.LINE_AA)


def overlay_image(
    top: np.ndarray,
    result: LayerResult,
    topview: TopView,
    footprint: np.ndarray | None = None,
    *,
    alpha: float = 0.75,
    caption: bool = True,
) -> np.ndarray:
    """Heatmap over the top view with failing regions and footprint outlined.

    Parameters
    ----------
    top : ndarray, shape (H, W) or (H, W, 3)
        The photo's top view the result was computed from.
    result : LayerResult
        Output of :func:`~layerwatch.analysis.scoring.analyze_layer` (needs
        ``heatmap``; ``mask`` limits colouring to considered blocks).
    topview : TopView
        Geometry of ``top`` (its shape must match).
    footprint : ndarray, shape (H, W), bool, optional
        Layer footprint, outlined in cyan. The scene channel's regions beside
        the print (``result.outside_regions``) are boxed in orange.
    alpha : float
        Opacity of the heatmap colour on a block of similarity 0; a block of
        similarity 1 gets 30 % of it.
    caption : bool
        Write layer, measure, threshold and a% in the top-left corner.

    Returns
    -------
    ndarray, shape (H, W, 3), uint8, RGB
    """
    shape = tuple(topview.shape)
    if np.asarray(top).shape[:2] != shape:
        raise AnalysisError(f"top view is {np.asarray(top).shape[:2]} px but the TopView is {shape}; pass matching images.")
    img = _to_rgb(top)
    if result.heatmap is None:
        return img
    heat = np.asarray(result.heatmap, dtype=np.float32)
    c, b, _ = _grid(result)
    mask = np.ones(heat.shape, bool) if result.mask is None else np.asarray(result.mask, bool)
    colours = _colormap(heat)
    col_px = np.stack([block_tiles(colours[..., k], shape, c, b) for k in range(3)], axis=2)
    sel = block_tiles(mask, shape, c, b, fill=False)
    # opacity grows with dissimilarity: matching areas get a light green tint,
    # failing blocks a strong red, so the photo stays readable
    weight = block_tiles(alpha * (0.3 + 0.7 * (1.0 - np.clip(heat, 0, 1))), shape, c, b)[sel][:, None]
    blend = (1 - weight) * img[sel].astype(np.float32) + weight * col_px[sel].astype(np.float32)
    img[sel] = np.clip(blend + 0.5, 0, 255).astype(np.uint8)
    if footprint is not None:
        fp = np.asarray(footprint, bool)
        if fp.shape != shape:
            raise AnalysisError(f"footprint is {fp.shape} px but the top view is {shape}; pass the matching mask.")
        _outline(img, fp, _FOOTPRINT_RGB, 1)
    anomalous = anomalous_blocks(result)
    thick = max(1, round(min(shape) / 300))
    _outline(img, block_tiles(anomalous, shape, c, b, fill=False), _REGION_RGB, thick)
    for r in result.outside_regions:  # the scene channel's changes beside the print (bed mm boxes)
        (u0, v0), (u1, v1) = np.round(topview.to_px(np.array([r.bbox_mm[:2], r.bbox_mm[2:]], float))).astype(int)
        cv2.rectangle(img, (u0, v1), (u1, v0), _OUTSIDE_RGB, thick)
    for r in (*result.regions, *result.outside_regions):  # the shape the region claims (what the IoU scores)
        polys = [np.round(topview.to_px(np.asarray(poly, float))).astype(np.int32) for poly in r.outline_mm if len(poly) >= 3]
        if polys:
            cv2.polylines(img, polys, True, _SHAPE_RGB, thick, lineType=cv2.LINE_AA)
    if caption:
        text = f"layer {result.layer}  {result.metric} < {result.threshold:.2f}  a% = {100 * result.anomaly_ratio:.1f}"
        if result.outside_anomalous_mm2 > 0:
            text += f"  beside {result.outside_anomalous_mm2:.0f} mm2"
        kind = region_label(result)
        if kind:
            text += f"  {kind}"
        scale = max(0.35, min(shape) / 1200)
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        cv2.rectangle(img, (0, 0), (tw + 8, th + base + 8), (0, 0, 0), -1)
        cv2.putText(img, text, (4, th + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def region_label(result: LayerResult) -> str:
    """The largest typed region's kind, confidence and displacement, e.g. ``"layer_shift 0.93 (2.1, -0.4) mm"``; ``""`` if none."""
    typed = [r for r in (*result.regions, *result.outside_regions) if r.kind]
    if not typed:
        return ""
    r = max(typed, key=lambda q: q.area_mm2)
    text = f"{r.kind} {r.kind_confidence:.2f}"
    if r.displacement_mm is not None:
        text += f" ({r.displacement_mm[0]:.1f}, {r.displacement_mm[1]:.1f}) mm"
    return text


def heatmap_image(result: LayerResult, scale: int = 8) -> np.ndarray:
    """The similarity heatmap alone, colour-mapped, one ``scale`` x ``scale`` square per block.

    Blocks not considered (``result.mask`` False) are drawn dark grey.

    Returns
    -------
    ndarray, shape (N*scale, M*scale, 3), uint8, RGB
    """
    if result.heatmap is None:
        raise AnalysisError("the result has no heatmap; analyse the layer with analyze_layer() first.")
    heat = np.asarray(result.heatmap, dtype=np.float32)
    rgb = _colormap(heat)
    if result.mask is not None:
        rgb[~np.asarray(result.mask, bool)] = (40, 40, 40)
    s = max(1, int(scale))
    return np.repeat(np.repeat(rgb, s, axis=0), s, axis=1)


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image as PNG, creating parent folders."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    arr = np.ascontiguousarray(rgb)
    if not cv2.imwrite(str(p), arr[..., ::-1] if arr.ndim == 3 else arr):
        raise AnalysisError(f"could not write {p}; check the folder exists and is writable.")
    return p


def write_overlay(
    path: str | Path,
    top: np.ndarray,
    result: LayerResult,
    topview: TopView,
    footprint: np.ndarray | None = None,
) -> Path:
    """Render :func:`overlay_image` and write it as PNG; returns the path."""
    return write_png(path, overlay_image(top, result, topview, footprint))
