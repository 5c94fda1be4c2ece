"""Changed as predicted: where the new layer was printed, the photo must have changed since the previous photo.

Series mode only (it needs the previous photo of the same print). The camera
is stationary, so between the photo of layer ``k`` and the previous analysed
photo (layer ``j < k``) every point of the new layer's footprint received new
plastic: its fine texture must differ. A patch missing from the infill or a
gap in a thin wall leaves the surface printed before in place, and the photo
shows there what the previous photo showed: **the same texture at the same
pixels**. That is what this channel looks for, per block of the layer's
footprint projected into the image on the layer's plane (the nothing-extruded
check's projection, :mod:`layerwatch.analysis.extrusion`, asks the same
question for the whole layer).

Per block of ``block_px`` working pixels, on the high-passed grey texture
(:func:`~layerwatch.analysis.extrusion.box_texture`: exposure drift, white
balance and a smooth change of light are a gain, which the high pass and the
per-block normalisation remove):

* **noise aware** (:func:`block_change`): the sensor noise, independent in
  the two photos, and the blur that changes from photo to photo lower the
  correlation of an unchanged block to about ``s / (s + n)`` (signal and
  noise variance; ``docs/checks.md``, the diagnosis). The noise variance
  ``n`` of the pair is half the median variance of ``a - b`` on the quiet
  blocks (off the new layer's projection: bed, earlier surfaces, which did
  not change); a block is judged only when the texture on its footprint
  pixels stands above it (``v >= (1 + min_snr) n`` in both photos), so that
  an unchanged block's correlation can reach ``min_ncc``; the correlation is
  the zero-mean NCC over the footprint pixels of the block
  (:func:`~layerwatch.analysis.extrusion.block_ncc`). (Correcting the NCC
  for the noise, ``cov / sqrt((v_a - n)(v_b - n))``, on whole blocks was
  tried first: a block mixes sparse infill with the unchanged holes between
  its lines, and clean layers gave more chance likenesses.)
* **against the printed twin**: a perimeter laid on its twin, or sparse infill
  repeating the line below, looks alike too, but one layer higher: the camera
  sees it shifted by the parallax of the height printed since the previous
  photo (:func:`parallax_px`). A block is *unchanged* when its correlation at
  the same pixels is at least ``min_ncc`` **and** exceeds the correlation with
  the previous texture shifted by that parallax by ``min_gain``.

Groups of unchanged blocks that were unchanged in the previous pair too
(:func:`persistent_groups`) are carried to the top view of the layer's plane
(the pipeline's own warp maps), kept on the footprint, and connected regions
of at least ``min_area_mm2`` become failing regions, typed ``thin_wall`` or
``infill_defect`` by what the G-code prints there (:func:`printed_kind`).
Blocks too flat to judge (a dark filament, a black or missing previous photo)
give no verdict, never a failure.

References
----------
Lewis (1995), "Fast normalized cross-correlation" (zero-mean NCC).
Petsiuk & Pearce (2022), eq. (5): a% = S_A / S_P.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import Field

from layerwatch.analysis.extrusion import block_ncc
from layerwatch.analysis.overlay import block_tiles
from layerwatch.analysis.result import LayerResult, Region
from layerwatch.analysis.scene_change import change_regions, top_coords
from layerwatch.analysis.scoring import anomaly_ratio
from layerwatch.gcode.toolpath import FEATURES, Toolpath
from layerwatch.geometry.topview import TopView
from layerwatch.settings_base import Section

__all__ = ["BlockChange", "LayerChangeSettings", "add_unchanged", "block_change", "blocks_on_top", "parallax_px", "persistent_groups", "printed_kind",
           "unchanged_regions"]

#: quiet blocks need this much texture variance (grey levels^2) in both photos to calibrate the noise on
QUIET_MIN_VAR = 1.0
#: fewest quiet blocks to calibrate on; fewer: the pair is not judged
MIN_QUIET_BLOCKS = 20
#: segment features that are walls / infill (the kind of an unchanged region, :func:`printed_kind`)
_WALLS = tuple(FEATURES.index(n) for n in ("perimeter", "external_perimeter"))
_INFILL = tuple(FEATURES.index(n) for n in ("infill", "solid_infill", "top_solid_infill", "bridge"))


class LayerChangeSettings(Section):
    """The "changed as predicted" channel (config section ``[layer_change]``; series mode only).

    Off in the built-in (paper) values, on in the recommended ones
    (:data:`layerwatch.pipeline.config.RECOMMENDED`), so ``--paper-settings``
    reproduces the paper's method. It compares textures on the nothing-extruded
    check's working image (``[extrusion] working_px``).

    Attributes
    ----------
    enabled : bool
        Look for footprint areas that did not change since the previous photo.
    min_area_mm2 : float
        Smallest connected unchanged area of the footprint that fails, mm^2 on the layer's plane.
    min_blocks : int
        Fewest 8-connected unchanged blocks a failing area needs (in the working image); the
        group must also touch a block unchanged in the previous pair (:func:`persistent_groups`).
    min_ncc : float
        NCC over a block's footprint pixels at the same pixels from which the block is unchanged.
    min_gain : float
        How much that correlation must exceed the correlation with the previous
        texture shifted by the layer's parallax (a twin printed on top).
    min_snr : float
        Texture variance above the noise a block needs, in units of the noise variance.
    block_px : int
        Block side, px of the working image.
    min_share : float
        Share of a block the projected footprint must cover for it to be judged.
    """

    enabled: bool = False
    min_area_mm2: float = Field(1.0, ge=0, le=2500)
    min_blocks: int = Field(1, ge=1, le=10000)
    min_ncc: float = Field(0.8, ge=0, le=1)
    min_gain: float = Field(0.2, ge=0, le=2)
    min_snr: float = Field(1.0, ge=0, le=100)
    block_px: int = Field(8, ge=2, le=64)
    min_share: float = Field(0.25, gt=0, le=1)


@dataclass
class BlockChange:
    """One photo pair's verdict per block (shape ``(n, m)`` = the working box in blocks).

    Attributes
    ----------
    ncc, ncc_twin : ndarray, float32, shape (n, m)
        NCC over the block's footprint pixels at the same pixels, and with the
        previous texture shifted by the parallax (0 where not judged).
    judged : ndarray, bool, shape (n, m)
        Footprint blocks with texture above the noise.
    unchanged : ndarray, bool, shape (n, m)
        Judged blocks that look as in the previous photo.
    noise : float
        Noise variance of one photo's texture, grey levels^2.
    """

    ncc: np.ndarray
    ncc_twin: np.ndarray
    judged: np.ndarray
    unchanged: np.ndarray
    noise: float


def _block_sum(v: np.ndarray, bp: int) -> np.ndarray:
    """Per-block mean of ``v`` (h, w) over whole ``bp`` blocks: (h // bp, w // bp) float32."""
    n, m = v.shape[0] // bp, v.shape[1] // bp
    return cv2.resize(np.ascontiguousarray(v[: n * bp, : m * bp], np.float32), (m, n), interpolation=cv2.INTER_AREA)


def _moments(a: np.ndarray, b: np.ndarray, bp: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-block variances of ``a`` and ``b`` and their covariance (whole blocks)."""
    ma, mb = _block_sum(a, bp), _block_sum(b, bp)
    va = np.maximum(_block_sum(a * a, bp) - ma * ma, 0)
    vb = np.maximum(_block_sum(b * b, bp) - mb * mb, 0)
    return va, vb, _block_sum(a * b, bp) - ma * mb


def parallax_px(maps: tuple[np.ndarray, np.ndarray], z: float, dz: float, step: int = 4) -> tuple[float, float]:
    """Image shift (working px) of a surface raised by ``dz`` mm at height ``z``: ``(dx, dy)``.

    A point seen at pixel ``p`` on the plane ``z`` is seen at ``p + d`` on the
    plane ``z - dz``: ``d = J^-1 (dT/dz) dz``, with ``J`` the top-view px per
    image px and ``dT/dz`` the top-view shift of a pixel's ray per mm of
    height (medians over every ``step``-th pixel of ``maps``: the print's box
    is small against its distance to the camera, so one shift serves it).

    Parameters
    ----------
    maps : (ndarray, ndarray)
        :func:`~layerwatch.analysis.scene_change.plane_maps` of the working box.
    z, dz : float
        Height of the new surface and the height printed since the previous photo, mm.
    step : int
        Subsampling of the medians, px.
    """
    A, B = (np.asarray(m)[:, ::step, ::step] for m in maps)
    tx, ty = top_coords((A, B), z)
    if tx.shape[0] < 2 or tx.shape[1] < 2 or dz == 0:
        return 0.0, 0.0
    J = np.array([[np.median(np.diff(tx, axis=1)), np.median(np.diff(tx, axis=0))],
                  [np.median(np.diff(ty, axis=1)), np.median(np.diff(ty, axis=0))]], np.float64) / step
    dT = np.array([np.median(B[0]), np.median(B[1])], np.float64) * dz
    if abs(np.linalg.det(J)) < 1e-9:
        return 0.0, 0.0
    d = np.linalg.solve(J, dT)
    return float(d[0]), float(d[1])


def _shifted(b: np.ndarray, d: tuple[float, float]) -> np.ndarray:
    """``b(p + d)`` (bilinear; borders replicated)."""
    M = np.array([[1.0, 0.0, d[0]], [0.0, 1.0, d[1]]], np.float32)
    return cv2.warpAffine(b, M, (b.shape[1], b.shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


def _masked_variance(v: np.ndarray, mask: np.ndarray, bp: int) -> np.ndarray:
    """Per-block variance of ``v`` over the ``mask`` pixels (0 where a block has none)."""
    k = mask.astype(np.float32)
    frac = np.maximum(_block_sum(k, bp), 1e-6)
    mean = _block_sum(v * k, bp) / frac
    return np.maximum(_block_sum(v * v * k, bp) / frac - mean * mean, 0)


def _aligned_box(mask: np.ndarray, bp: int) -> tuple[slice, slice] | None:
    """Rows and columns of ``mask``'s bounding box, grown to whole ``bp`` blocks of the image (``None``: empty)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    n, m = mask.shape[0] // bp, mask.shape[1] // bp
    r0, c0 = min(rows[0] // bp, n), min(cols[0] // bp, m)
    r1, c1 = min(rows[-1] // bp + 1, n), min(cols[-1] // bp + 1, m)
    return slice(r0 * bp, r1 * bp), slice(c0 * bp, c1 * bp)


def block_change(a: np.ndarray, b: np.ndarray, surface: np.ndarray, near: np.ndarray,
                 parallax: tuple[float, float], settings: LayerChangeSettings) -> BlockChange | None:
    """Which blocks of the new layer's projected footprint look as in the previous photo (module notes).

    Parameters
    ----------
    a, b : ndarray, float32, shape (h, w)
        High-passed textures of the new and the previous photo (:func:`~layerwatch.analysis.extrusion.box_texture`).
    surface : ndarray, bool, shape (h, w)
        The new layer's footprint on its plane, seen through the camera.
    near : ndarray, bool, shape (h, w)
        Pixels the print may have changed since the previous photo (the new
        layer's projection with its walls, grown): never quiet.
    parallax : (float, float)
        :func:`parallax_px` of the height printed since the previous photo.
    settings : LayerChangeSettings

    Returns
    -------
    BlockChange or None
        ``None`` when the pair cannot be calibrated (fewer than
        :data:`MIN_QUIET_BLOCKS` textured quiet blocks: a black, blank or
        foreign previous photo).
    """
    bp = settings.block_px
    va, vb, cov = _moments(a, b, bp)
    calm = (_block_sum(near.astype(np.float32), bp) == 0) & (np.minimum(va, vb) > QUIET_MIN_VAR)
    if int(calm.sum()) < MIN_QUIET_BLOCKS:
        return None
    noise = 0.5 * float(np.median((va + vb - 2 * cov)[calm]))
    ncc, twin = np.zeros_like(va), np.zeros_like(va)
    scored = np.zeros(va.shape, bool)
    box = _aligned_box(surface, bp)
    texture = np.zeros_like(va)
    if box is not None:  # the footprint's blocks only (block_ncc per block: the same values as on the whole box)
        blocks = (slice(box[0].start // bp, box[0].stop // bp), slice(box[1].start // bp, box[1].stop // bp))
        x, y, m = a[box], b[box], surface[box]
        ncc[blocks], scored[blocks] = block_ncc(x, y, m, bp, settings.min_share)
        twin[blocks] = block_ncc(x, _shifted(b, parallax)[box], m, bp, settings.min_share)[0]
        texture[blocks] = np.minimum(_masked_variance(x, m, bp), _masked_variance(y, m, bp))
    judged = scored & (texture >= (1.0 + settings.min_snr) * noise)
    unchanged = judged & (ncc >= settings.min_ncc) & (ncc - twin >= settings.min_gain)
    return BlockChange(np.where(judged, ncc, 0).astype(np.float32), np.where(judged, twin, 0).astype(np.float32),
                       judged, unchanged, noise)


def persistent_groups(unchanged: np.ndarray, previous: np.ndarray | None, min_blocks: int) -> np.ndarray:
    """The 8-connected groups of ``unchanged`` blocks that were unchanged in the previous pair too.

    A missing patch stays missing: where the nozzle left a gap, the next photo
    shows the same old surface again (the hole deepens under new layers
    around it), so its blocks are unchanged in two pairs in a row. A clean
    layer's chance coincidences (a bead that happens to look like the one
    below) do not repeat at the same place. A group is kept when it has at
    least ``min_blocks`` blocks and one of them is, or touches, a block that
    was unchanged in ``previous``.

    Parameters
    ----------
    unchanged : ndarray, bool, shape (n, m)
        This pair's unchanged blocks (:attr:`BlockChange.unchanged`).
    previous : ndarray, bool, shape (n, m), or None
        The previous pair's (same working box); ``None``: none, nothing is kept.
    min_blocks : int

    Returns
    -------
    ndarray, bool, shape (n, m)
    """
    if previous is None or previous.shape != unchanged.shape or not unchanged.any():
        return np.zeros(unchanged.shape, bool)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(unchanged.astype(np.uint8), connectivity=8)
    near = cv2.dilate(previous.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    ids = np.unique(lab[unchanged & near])
    ids = ids[(ids > 0) & (stats[ids, cv2.CC_STAT_AREA] >= min_blocks)]
    return np.isin(lab, ids)


def blocks_on_top(blocks: np.ndarray, block_px: int, origin: tuple[int, int], scale: tuple[float, float],
                  source: tuple[np.ndarray, np.ndarray], where: np.ndarray) -> np.ndarray:
    """Top-view pixels whose source pixel in the working image lies in a True block.

    Parameters
    ----------
    blocks : ndarray, bool, shape (n, m)
        Blocks of ``block_px`` working px, the first one's corner at ``origin``.
    block_px : int
    origin : (int, int)
        Row and column of the blocks' corner in the working image, px.
    scale : (float, float)
        Working px per photo px, x and y.
    source : (ndarray, ndarray), float32, shape (H, W)
        Photo px ``(x, y)`` seen at each top-view pixel on the layer's plane
        (the pipeline's warp maps, :meth:`~layerwatch.geometry.warp.TopViewWarper.maps`).
    where : ndarray, bool, shape (H, W)
        Top-view pixels to look up (the footprint, seen by the camera).

    Returns
    -------
    ndarray, bool, shape (H, W)
    """
    out = np.zeros(where.shape, bool)
    vv, uu = np.nonzero(where)
    if vv.size == 0 or not blocks.any():
        return out
    wx = (source[0][vv, uu] + 0.5) * scale[0] - origin[1]  # working px (pixel i spans [i, i + 1))
    wy = (source[1][vv, uu] + 0.5) * scale[1] - origin[0]
    bi, bj = np.floor(wy / block_px).astype(np.int64), np.floor(wx / block_px).astype(np.int64)
    ok = (bi >= 0) & (bi < blocks.shape[0]) & (bj >= 0) & (bj < blocks.shape[1])
    out[vv[ok], uu[ok]] = blocks[bi[ok], bj[ok]]
    return out


def printed_kind(toolpath: Toolpath, index: int, mask: np.ndarray, topview: TopView) -> str:
    """``"thin_wall"`` when walls are most of what layer ``index`` prints inside the top-view ``mask``, else ``"infill_defect"``.

    Segments count by their length inside the mask (sampled every top-view pixel).
    """
    sl = toolpath.layer_slice(index)
    p0, p1 = toolpath.start[sl][:, :2], toolpath.end[sl][:, :2]
    feats = toolpath.feature[sl]
    use = np.isin(feats, _WALLS + _INFILL)
    if not use.any():
        return "infill_defect"
    p0, p1, feats = p0[use], p1[use], feats[use]
    steps = np.maximum(1, np.ceil(np.hypot(*(p1 - p0).T) * topview.px_per_mm)).astype(int)
    seg = np.repeat(np.arange(len(p0)), steps)
    t = (np.arange(seg.size) - np.repeat(np.cumsum(steps) - steps, steps) + 0.5) / np.repeat(steps, steps)
    uv = np.round(topview.to_px(p0[seg] + t[:, None] * (p1 - p0)[seg])).astype(int)
    h, w = mask.shape
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    hit = np.zeros(seg.size, bool)
    hit[ok] = mask[uv[ok, 1], uv[ok, 0]]
    walls = int(np.isin(feats[seg[hit]], _WALLS).sum())
    return "thin_wall" if walls > hit.sum() - walls else "infill_defect"


def unchanged_regions(unchanged_top: np.ndarray, footprint: np.ndarray, toolpath: Toolpath, index: int,
                      topview: TopView, min_area_mm2: float) -> tuple[np.ndarray, list[Region]]:
    """The connected unchanged areas of the footprint, as typed failing regions.

    Parameters
    ----------
    unchanged_top : ndarray, bool, shape (H, W)
        Top-view pixels (plane of layer ``index``) whose block was unchanged.
    footprint : ndarray, bool, shape (H, W)
        The layer's footprint.
    toolpath : Toolpath
    index : int
        The layer.
    topview : TopView
    min_area_mm2 : float
        Smaller areas are dropped.

    Returns
    -------
    mask : ndarray, bool, shape (H, W)
        Pixels of the kept regions.
    regions : list of Region
        Largest first; ``kind`` ``"thin_wall"`` or ``"infill_defect"``
        (:func:`printed_kind`), ``kind_confidence`` the share of the region's
        footprint found unchanged, ``outside_fraction`` 0.
    """
    on = unchanged_top & footprint
    n, lab, stats, _ = cv2.connectedComponentsWithStats(on.astype(np.uint8), connectivity=8)
    area = stats[:, cv2.CC_STAT_AREA] / topview.px_per_mm**2
    keep = np.flatnonzero(area >= min_area_mm2)
    keep = keep[keep > 0]
    mask = np.isin(lab, keep) if keep.size else np.zeros_like(on)
    sim = np.where(mask, 0.0, 1.0).astype(np.float32)
    regions = change_regions(mask, sim, topview, min_area_mm2)
    for r in regions:
        x0, y0, x1, y1 = r.bbox_mm
        (u0, v0), (u1, v1) = np.round(topview.to_px(np.array([[x0, y1], [x1, y0]], float))).astype(int)
        box = (slice(max(v0, 0), v1 + 1), slice(max(u0, 0), u1 + 1))
        r.kind = printed_kind(toolpath, index, _crop_mask(mask, box), topview)
        fp = int(np.count_nonzero(footprint[box]))
        r.kind_confidence = round(float(np.count_nonzero(mask[box])) / max(fp, 1), 3)
        r.outside_fraction = 0.0
    return mask, regions


def _crop_mask(mask: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    out = np.zeros_like(mask)
    out[box] = mask[box]
    return out


def add_unchanged(res: LayerResult, mask: np.ndarray, regions: list[Region], topview: TopView) -> float:
    """Count the unchanged regions into ``res``: its ``regions`` and a% (eq. 5 over the printed area).

    ``S_A`` grows by the area of ``mask`` that no anomalous HOG block's tile
    already covers (each printed square counts once); ``S_P`` is unchanged.

    Parameters
    ----------
    res : LayerResult
        An analysed layer (``heatmap``, ``mask`` and ``grid`` of its comparison).
    mask : ndarray, bool, shape (H, W)
        Top-view pixels of ``regions``.
    regions : list of Region
    topview : TopView

    Returns
    -------
    float
        The area added to ``S_A``, mm^2.

    References
    ----------
    Petsiuk & Pearce (2022), eq. (5).
    """
    if not regions:
        return 0.0
    covered = np.zeros(mask.shape, bool)
    if res.heatmap is not None and res.mask is not None and res.grid is not None:
        anom = np.asarray(res.mask, bool) & (np.asarray(res.heatmap) < res.threshold)
        covered = block_tiles(anom, mask.shape, res.grid.cell_px, res.grid.block_cells, fill=False).astype(bool)
    added = float(np.count_nonzero(mask & ~covered)) / topview.px_per_mm**2
    res.anomalous_area_mm2 = float(res.anomalous_area_mm2) + added
    res.anomaly_ratio = anomaly_ratio(1, res.anomalous_area_mm2, float(res.printed_area_mm2))
    res.regions = sorted([*res.regions, *regions], key=lambda r: -r.area_mm2)
    return added
