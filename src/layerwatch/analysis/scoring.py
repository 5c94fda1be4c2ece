"""Score one layer: HOG of photo and reference, heatmap, anomaly ratio, regions.

Block geometry (skimage's layout). With cells of ``c`` px and blocks of
``b x b`` cells, block ``(i, j)`` covers pixel rows ``[i*c, i*c + b*c)`` and
columns ``[j*c, j*c + b*c)``; blocks slide by one cell, so they overlap.
For areas every block stands for its *tile*: the ``c x c`` px square at the
block's centre (rows ``[i*c + o, i*c + o + c)``, ``o = (b - 1) * c // 2``).
Tiles of neighbouring blocks do not overlap, so one anomalous block counts
``(c / px_per_mm)**2`` mm^2 (1.44 mm^2 for 8-px cells at 6.67 px/mm).

Block size and smallest defect. A block is ``b * c / px_per_mm`` mm wide:
2 x 8 px / 6.67 px/mm = 2.4 mm with the paper's parameters. The paper quotes
4.8 mm; that is 32 px at 6.67 px/mm, i.e. the side of a block made of 2 x 2
cells of 16 px (or of 8-px cells at half the scale, 3.33 px/mm). We could not
reconcile it with 8-px cells at 6.67 px/mm and report the geometric value;
:func:`block_geometry` gives both numbers, and 4-px cells halve them.

Which blocks count. Blocks that have a cell within
``settings.footprint_margin_mm`` of a cell containing footprint pixels (cell
centre to cell centre, so the margin is resolved to whole cells, 1.2 mm for
the defaults; spaghetti or a detached part beside the print counts although
the reference is empty there) and that lie wholly inside ``valid`` (pixels
the camera saw). A block is anomalous when its similarity is
below ``settings.threshold`` (T_S); anomalous blocks in connected groups
(8-connectivity) smaller than ``settings.min_region_blocks`` are dropped.

Areas (eq. 5). ``S_P`` = footprint pixels inside ``valid`` / px_per_mm^2;
``S_A`` = number of anomalous blocks x tile area (footprint and margin);
``a% = min(1, S_A / S_P)``.

Images. Colour images are reduced to grey by the channel mean (independent
of BGR/RGB order). Intensities are put on a 0-255 scale: uint8 as is, uint16
/ 257, float images are taken as 0-1 and multiplied by 255. Blocks whose
mean gradient magnitude on that scale is below ``settings.min_gradient`` in
*both* images are featureless (set to zero, similarity 1): sensor noise on a
bare bed then matches an empty reference, while material where the reference
is flat (or a flat photo where the reference has structure) still scores
low. Both images must have the same size and dtype.

References
----------
Petsiuk & Pearce (2022), Section 2.4, eqs. (4)-(5), Figs. 13 and 15.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
from scipy import ndimage

from layerwatch.analysis.block_masks import touching
from layerwatch.analysis.failure_kinds import MOVED_KINDS
from layerwatch.analysis.hog import block_energy, hog_blocks, hog_cell_histograms, normalize_blocks
from layerwatch.analysis.metrics import similarity, similarity_all
from layerwatch.analysis.result import BlockGrid, LayerResult, MetricScore, Region
from layerwatch.analysis.settings import METRIC_NAMES, AnalysisSettings
from layerwatch.errors import AnalysisError
from layerwatch.geometry.topview import TopView

__all__ = ["analyze_layer", "anomaly_ratio", "block_geometry", "block_hogs", "grey_u8", "grow_regions", "growth_reach",
           "near_footprint", "area_weight", "printed_weight", "reference_hog", "tile_share",
           "to_grey255", "moved_uncounted_mm2", "whole_view_score", "PART_GAP_MM"]

#: ``cv2.transform`` row giving ``floor((B + G + R) / 3)`` of uint8 pixels: cv2 rounds
#: ``s / 3 - 1/3`` to nearest, whose fraction is never near .5 (checked on all 2**24 colours)
_MEAN3_FLOOR = np.array([[1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0, -1.0 / 3.0]])


def block_geometry(cell_px: int = 8, block_cells: int = 2, px_per_mm: float = 6.67) -> dict[str, float]:
    """Sizes of the analysis grid in millimetres.

    Returns
    -------
    dict
        ``cell_mm`` (cell side), ``block_mm`` (block side = analysis window,
        2.4 mm for 8-px cells at 6.67 px/mm), ``stride_mm`` (= cell_mm),
        ``tile_area_mm2`` (area one block stands for), and
        ``paper_block_mm`` (twice ``block_mm``: the paper's 4.8 mm figure,
        which matches 16-px cells; see the module notes).
    """
    cell_mm = cell_px / px_per_mm
    return {
        "cell_mm": cell_mm,
        "block_mm": block_cells * cell_mm,
        "stride_mm": cell_mm,
        "tile_area_mm2": cell_mm * cell_mm,
        "paper_block_mm": 2 * block_cells * cell_mm,
    }


def to_grey255(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Grey (H, W) image on a 0-255 scale (see module notes); raises on NaN/bad dtype.

    Grey uint8 input is returned unchanged (no copy); everything else becomes float32.
    """
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] in (1, 3, 4):
        arr = arr[..., :3] if arr.shape[2] == 4 else arr
    elif arr.ndim != 2:
        raise AnalysisError(f"{name} must be (H, W) grey or (H, W, 3) colour, got shape {arr.shape}.")
    if arr.dtype == np.uint8:
        if arr.ndim == 2:
            return arr
        scale = 1.0
    elif arr.dtype == np.uint16:
        scale = 1.0 / 257.0
    elif arr.dtype.kind == "f":
        scale = 255.0
    else:
        raise AnalysisError(f"{name} has dtype {arr.dtype}; pass uint8, uint16 or float (0-1) images.")
    grey = arr.astype(np.float32) if arr.ndim == 2 else arr.astype(np.float32).mean(axis=2)
    if scale != 1.0:
        grey *= np.float32(scale)
    if not np.all(np.isfinite(grey)):
        raise AnalysisError(f"{name} contains NaN or infinite pixels; fix the image before the analysis.")
    return grey


def grey_u8(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Grey uint8 (H, W) image: :func:`to_grey255` truncated to whole grey levels.

    The one grey conversion of a warped photo (the per-layer step, ``compare``,
    overlays); grey uint8 input is returned unchanged. Colour uint8 takes one
    ``cv2.transform`` (the same whole grey levels as the float mean, ten
    times faster on a 600 x 600 top view).
    """
    arr = np.asarray(image)
    if arr.dtype == np.uint8 and arr.ndim == 3 and arr.shape[2] in (3, 4):
        return cv2.transform(np.ascontiguousarray(arr[..., :3]), _MEAN3_FLOOR)
    grey = to_grey255(image, name)
    return grey if grey.dtype == np.uint8 else np.clip(grey, 0, 255).astype(np.uint8)


def anomaly_ratio(n_anomalous, tile_mm2: float, printed_mm2: float):
    """a% of eq. (5): ``min(1, S_A / S_P)`` with ``S_A = n_anomalous * tile_mm2``; 0 when nothing is printed.

    Parameters
    ----------
    n_anomalous : int or ndarray of int
        Anomalous blocks (any shape: the evaluation passes counts per threshold).
    tile_mm2 : float
        Area one block stands for, mm^2 (module notes).
    printed_mm2 : float
        ``S_P``, printed area, mm^2.

    Returns
    -------
    float or ndarray of float64, same shape as ``n_anomalous``, in [0, 1]

    References
    ----------
    Petsiuk & Pearce (2022), eq. (5).
    """
    n = np.asarray(n_anomalous, np.float64)
    out = np.minimum(1.0, n * tile_mm2 / printed_mm2) if printed_mm2 > 0 else np.zeros_like(n)
    return float(out) if out.ndim == 0 else out


def moved_uncounted_mm2(res: LayerResult) -> float:
    """The image area of a moved part's failing blocks that S_A leaves out, mm^2.

    With ``anomalous_area = "printed"`` a block beside the layer's part adds
    nothing to S_A (:func:`printed_weight`): right for an object or a strand
    beside a small layer, which the scene channel reports as its own figure,
    but a part that moved (a layer shift, a detached part: regions typed one of
    :data:`~layerwatch.analysis.failure_kinds.MOVED_KINDS`) shows *by being
    beside its footprint*: a 2 mm shift of a 13 mm^2 cube leaves one block
    beside the footprint and none on it. For those regions the blocks' share
    beside the part counts: ``area_mm2 * outside_fraction`` of each, at most
    the layer's :attr:`~layerwatch.analysis.result.LayerResult.uncounted_mm2`
    (a tile inside the part's closed outline already counts whole).

    Parameters
    ----------
    res : LayerResult
        A typed result (the pipeline's; untyped regions add nothing).

    Returns
    -------
    float
        mm^2, ``0 <= value <= res.uncounted_mm2``.
    """
    moved = sum(float(r.area_mm2) * float(r.outside_fraction) for r in res.regions if r.kind in MOVED_KINDS)
    return float(min(max(moved, 0.0), max(float(res.uncounted_mm2), 0.0)))


def whole_view_score(res: LayerResult) -> float:
    """The layer's whole-view score: a% (eq. 5) plus what it shows beside the printed layer, over ``S_P``.

    ``a% + (outside_anomalous_mm2 + moved_uncounted_mm2) / max(S_P, 1 mm^2)``: the
    scene channel's change beside the print (issue 18's own figure beside
    eq. 5) and a moved part's blocks beside its footprint
    (:func:`moved_uncounted_mm2`); the paper's a% when neither is there. A
    fraction (may exceed 1); the evaluation ranks layers by it (AUROC).

    Parameters
    ----------
    res : LayerResult

    Returns
    -------
    float
    """
    beside = float(res.outside_anomalous_mm2) + moved_uncounted_mm2(res)
    return float(res.anomaly_ratio) + beside / max(float(res.printed_area_mm2), 1.0)


def _presmoothed(grey: np.ndarray, settings: AnalysisSettings) -> np.ndarray:
    """The grey image pre-filtered as the analysis compares it (Gaussian of ``presmooth_px``; as is when 0)."""
    if settings.presmooth_px <= 0:
        return grey
    return cv2.GaussianBlur(np.asarray(grey, np.float32), (0, 0), float(settings.presmooth_px),
                            borderType=cv2.BORDER_REPLICATE)


def reference_hog(reference: np.ndarray, settings: AnalysisSettings) -> tuple[np.ndarray, np.ndarray]:
    """Cell histograms and block energies of a reference as :func:`block_hogs` uses them.

    A reference does not change between photos, so the per-layer step
    computes this once with the reference (``Reference.hog``) and passes it
    to :func:`analyze_layer`; the block normalisation (a fraction of the
    cost) runs per call, so what is kept is the cell histograms, a quarter
    of the block tensor. The arrays are returned read-only.

    Returns
    -------
    cells : ndarray, shape (R, C, bins), float64
        :func:`~layerwatch.analysis.hog.hog_cell_histograms` of the pre-filtered grey reference.
    energy : ndarray, shape (R - block_cells + 1, C - block_cells + 1), float64
        Mean gradient magnitude per block (the featureless test of :func:`block_hogs`).

    Raises
    ------
    AnalysisError
        Bad image, or smaller than one HOG block.
    """
    grey = _presmoothed(to_grey255(reference, "reference"), settings)
    b = int(settings.block_cells)
    if grey.shape[0] // settings.cell_px < b or grey.shape[1] // settings.cell_px < b:
        raise AnalysisError(f"reference {grey.shape[1]}x{grey.shape[0]} px is smaller than one HOG block; "
                            "use a larger top view or smaller cells.")
    cells = hog_cell_histograms(grey, settings.cell_px, settings.bins, settings.gamma, settings.votes)
    energy = block_energy(cells, b)
    cells.flags.writeable = energy.flags.writeable = False
    return cells, energy


def block_hogs(top: np.ndarray, reference: np.ndarray, settings: AnalysisSettings,
               ref_hog: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """HOG block tensors of photo and reference as the analysis compares them.

    Both images go to grey 0-255 (:func:`to_grey255`), are pre-filtered when
    ``settings.presmooth_px > 0`` (Gaussian, same sigma for both), and block
    pairs that are featureless (mean gradient magnitude below
    ``settings.min_gradient`` in both images, or in the photo with the
    reference below ``flat_tolerance`` times that) are zeroed so that they
    score similarity 1. ``ref_hog`` is the reference's :func:`reference_hog`
    when it was computed ahead (same ``settings``); it is not modified.

    Returns
    -------
    h_top, h_ref : ndarray, shape (N, M, k), float64
        ``k = block_cells**2 * bins`` (36 for the paper's parameters).
    """
    h_top, e_top = hog_blocks(_presmoothed(to_grey255(top, "photo top view"), settings), cell_px=settings.cell_px,
                              block_cells=settings.block_cells, bins=settings.bins, block_norm=settings.block_norm,
                              gamma=settings.gamma, return_energy=True, votes=settings.votes)
    cells, e_ref = ref_hog if ref_hog is not None else reference_hog(reference, settings)
    h_ref = normalize_blocks(cells, settings.block_cells, settings.block_norm)
    # featureless photo; reference featureless or only faintly textured (flat_tolerance >= 1, validated)
    flat = (e_top < settings.min_gradient) & (e_ref < settings.flat_tolerance * settings.min_gradient)
    h_top[flat] = 0.0  # featureless in both: identical (similarity 1)
    h_ref[flat] = 0.0
    return h_top, h_ref


def near_footprint(
    footprint: np.ndarray,
    grid_shape: tuple[int, int],
    topview: TopView,
    settings: AnalysisSettings,
    margin_mm: float,
    valid: np.ndarray | None = None,
    footprint_integral: np.ndarray | None = None,
) -> np.ndarray:
    """Blocks with a cell within ``margin_mm`` of a footprint cell and wholly seen by the camera.

    Parameters
    ----------
    footprint : ndarray, shape (H, W), bool
    grid_shape : (N, M)
        Block grid of the HOG (``hog_blocks`` output's first two axes).
    topview : TopView
    settings : AnalysisSettings
        ``cell_px`` and ``block_cells``.
    margin_mm : float
        Cell centre to cell centre, resolved to whole cells.
    valid : ndarray, shape (H, W), bool, optional
        Pixels the camera saw; blocks with an unseen pixel are left out.
    footprint_integral : ndarray, optional
        ``cv2.integral`` of ``footprint`` when the caller has it.

    Returns
    -------
    ndarray, shape (N, M), bool
    """
    c, b = settings.cell_px, settings.block_cells
    n, m = grid_shape
    foot_int = _integral(np.asarray(footprint, bool)) if footprint_integral is None else footprint_integral
    cells_r, cells_c = np.arange(n + b - 1) * c, np.arange(m + b - 1) * c
    out = _near_blocks(_box_sums(foot_int, cells_r, cells_c, c), b, margin_mm * topview.px_per_mm / c)
    if valid is not None:
        out &= _box_sums(_integral(~np.asarray(valid, bool)), np.arange(n) * c, np.arange(m) * c, b * c) == 0
    return out


def growth_reach(
    considered: np.ndarray,
    footprint: np.ndarray,
    topview: TopView,
    settings: AnalysisSettings,
    valid: np.ndarray | None = None,
    footprint_integral: np.ndarray | None = None,
) -> np.ndarray:
    """Blocks a drawn region may grow into: the considered blocks, or those within ``grow_margin_mm``.

    Parameters
    ----------
    considered : ndarray, shape (N, M), bool
        Blocks within ``footprint_margin_mm`` (:func:`near_footprint`).
    footprint, topview, settings, valid, footprint_integral
        As for :func:`near_footprint`.

    Returns
    -------
    ndarray, shape (N, M), bool
    """
    if settings.grow_margin_mm <= settings.footprint_margin_mm:
        return considered
    return near_footprint(footprint, considered.shape, topview, settings, settings.grow_margin_mm, valid,
                          footprint_integral)


def grow_regions(seeds: np.ndarray, loose: np.ndarray) -> np.ndarray:
    """Hysteresis: the 8-connected components of ``loose`` that contain a seed.

    Parameters
    ----------
    seeds : ndarray, shape (N, M), bool
        Anomalous blocks (similarity below T_S).
    loose : ndarray, shape (N, M), bool
        Blocks below the looser threshold (a superset of ``seeds`` is expected;
        seeds outside it are kept).

    Returns
    -------
    ndarray, shape (N, M), bool
    """
    return touching(loose | seeds, seeds)


def tile_share(footprint: np.ndarray, grid_shape: tuple[int, int], cell_px: int, block_cells: int,
               footprint_integral: np.ndarray | None = None) -> np.ndarray:
    """Printed share of each block's tile: the footprint's fraction of the cell at the block's centre.

    The blocks overlap with a stride of one cell, so each stands for one cell-sized tile
    (what a% of eq. 5 counts per anomalous block).

    Parameters
    ----------
    footprint : ndarray, shape (H, W), bool
    grid_shape : (N, M)
        Block grid of the HOG.
    cell_px, block_cells : int
    footprint_integral : ndarray, optional
        ``cv2.integral`` of ``footprint`` when the caller has it.

    Returns
    -------
    ndarray, shape (N, M), float64
        In [0, 1].
    """
    c, b = int(cell_px), int(block_cells)
    n, m = grid_shape
    foot_int = _integral(np.asarray(footprint, bool)) if footprint_integral is None else footprint_integral
    off = (b - 1) * c // 2
    return _box_sums(foot_int, np.arange(n) * c + off, np.arange(m) * c + off, c) / float(c * c)


#: gaps of a layer's footprint up to about this wide (mm) are the part's own inside (sparse-infill cells,
#: the room between perimeters and infill), not beside it: :func:`printed_weight`
PART_GAP_MM = 6.0


def printed_weight(share: np.ndarray, tile_mm: float, gap_mm: float = PART_GAP_MM) -> np.ndarray:
    """What each block's tile adds to S_A with ``anomalous_area = "printed"``: the part's share of the tile.

    The part at this layer is the footprint with its own gaps closed (a morphological closing of the
    tiles holding printed pixels, over gaps up to about ``gap_mm``): a tile inside it counts whole (a
    sparse-infill cell shows the layers below through the part, as in the paper), a tile on its edge
    counts its printed share, a tile beside it (the bed, a hollow part's floor through a wider opening,
    a wall's face below the layer) counts nothing.

    Parameters
    ----------
    share : ndarray, shape (N, M)
        :func:`tile_share` of the footprint.
    tile_mm : float
        Side of a tile (one cell), mm.
    gap_mm : float
        Widest gap of the footprint taken as the part's inside, mm.

    Returns
    -------
    ndarray, shape (N, M), float64
        In [0, 1].
    """
    occ = (np.asarray(share) > 0).astype(np.uint8)
    r = max(int(np.ceil(0.5 * gap_mm / tile_mm)), 1)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    closed = cv2.morphologyEx(occ, cv2.MORPH_CLOSE, disk, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    inside = cv2.erode(closed, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    return np.where(inside, 1.0, np.asarray(share, np.float64))


def area_weight(share: np.ndarray, tile_mm: float, mode: str) -> np.ndarray:
    """What each block's tile adds to S_A under ``[analysis] anomalous_area = mode``, shape of ``share``.

    ``"tiles"``: 1; ``"printed"``: :func:`printed_weight`; ``"part"``: 1 where the tile holds a printed
    pixel or lies inside the part, else 0 (only tiles wholly beside the part are left out).
    """
    if mode == "tiles":
        return np.ones(np.shape(share))
    w = printed_weight(share, tile_mm)
    return np.where(np.asarray(share) > 0, 1.0, w) if mode == "part" else w


def _mask(arr, shape, name) -> np.ndarray:
    m = np.asarray(arr)
    if m.shape != shape:
        raise AnalysisError(f"{name} mask has shape {m.shape} but the images are {shape}; render it for the same top view.")
    return m.astype(bool, copy=False)


def _integral(mask: np.ndarray) -> np.ndarray:
    """Summed-area table of a bool mask, shape (H+1, W+1), int32 (TopView caps H*W at 64e6)."""
    return cv2.integral(mask.view(np.uint8))


def _box_sums(integ: np.ndarray, r0: np.ndarray, c0: np.ndarray, size: int) -> np.ndarray:
    """Pixel counts in squares ``[r0, r0+size) x [c0, c0+size)`` from a summed-area table."""
    r1 = np.minimum(r0 + size, integ.shape[0] - 1)
    c1 = np.minimum(c0 + size, integ.shape[1] - 1)
    return integ[r1][:, c1] - integ[r0][:, c1] - integ[r1][:, c0] + integ[r0][:, c0]


def _near_blocks(cell_counts: np.ndarray, block_cells: int, margin_cells: float) -> np.ndarray:
    """Blocks with a cell whose centre is within ``margin_cells`` of a footprint cell."""
    occ = cell_counts > 0
    if not occ.any():
        return np.zeros((occ.shape[0] - block_cells + 1, occ.shape[1] - block_cells + 1), bool)
    near = ndimage.distance_transform_edt(~occ) <= margin_cells + 1e-9 if margin_cells > 0 else occ
    b = block_cells
    n, m = near.shape[0] - b + 1, near.shape[1] - b + 1
    out = np.zeros((n, m), bool)
    for di in range(b):
        for dj in range(b):
            out |= near[di : di + n, dj : dj + m]
    return out


def _regions(anom, heat, foot_frac, grid, topview) -> tuple[np.ndarray, list[Region]]:
    """Label anomalous blocks; drop small groups; describe the rest in bed mm."""
    c, b, min_blocks = grid["cell_px"], grid["block_cells"], grid["min_region_blocks"]
    labels, n = ndimage.label(anom, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return anom, []
    lab = labels.ravel()
    counts = np.bincount(lab, minlength=n + 1)
    keep = counts >= min_blocks
    keep[0] = False
    anom = keep[labels]
    off = (b - 1) * c // 2
    tile_mm2 = (c / topview.px_per_mm) ** 2
    ids = np.nonzero(keep)[0]
    if ids.size == 0:
        return anom, []
    # per-region statistics in one pass each (bincount over labels)
    ii, jj = np.indices(labels.shape)
    cnt = counts[ids].astype(np.float64)

    def per(values):
        return np.bincount(lab, weights=np.asarray(values, np.float64).ravel(), minlength=n + 1)[ids]

    mean_s = per(heat) / cnt
    inside = per(foot_frac) / cnt
    min_s = np.asarray(ndimage.minimum(heat, labels, ids), dtype=np.float64).reshape(-1)
    # tile extents in pixel coordinates (OpenCV: pixel p spans [p-0.5, p+0.5])
    slices = ndimage.find_objects(labels)
    r0 = np.array([slices[k - 1][0].start for k in ids])
    r1 = np.array([slices[k - 1][0].stop - 1 for k in ids])
    c0 = np.array([slices[k - 1][1].start for k in ids])
    c1 = np.array([slices[k - 1][1].stop - 1 for k in ids])
    lo = topview.to_mm(np.stack([c0 * c + off - 0.5, r1 * c + off + c - 0.5], axis=1))
    hi = topview.to_mm(np.stack([c1 * c + off + c - 0.5, r0 * c + off - 0.5], axis=1))
    centre_u = per(jj * c + (b * c - 1) / 2.0) / cnt
    centre_v = per(ii * c + (b * c - 1) / 2.0) / cnt
    centre = topview.to_mm(np.stack([centre_u, centre_v], axis=1))
    regions = [
        Region(
            area_mm2=float(cnt[t] * tile_mm2),
            bbox_mm=(float(lo[t, 0]), float(lo[t, 1]), float(hi[t, 0]), float(hi[t, 1])),
            centroid_mm=(float(centre[t, 0]), float(centre[t, 1])),
            n_blocks=int(cnt[t]),
            mean_similarity=float(mean_s[t]),
            min_similarity=float(min_s[t]),
            outside_fraction=float(np.clip(1.0 - inside[t], 0.0, 1.0)),
        )
        for t in range(ids.size)
    ]
    regions.sort(key=lambda r: (-r.area_mm2, r.min_similarity))
    return anom, regions


def _check_images(top, reference, topview: TopView) -> tuple[np.ndarray, np.ndarray]:
    """Both images as arrays of the same size and dtype, the size of ``topview`` (else AnalysisError)."""
    top_a, ref_a = np.asarray(top), np.asarray(reference)
    if top_a.shape[:2] != ref_a.shape[:2]:
        raise AnalysisError(f"photo top view is {top_a.shape[:2]} px but the reference is {ref_a.shape[:2]}; render the reference for the same top view.")
    if top_a.dtype != ref_a.dtype:
        raise AnalysisError(f"photo ({top_a.dtype}) and reference ({ref_a.dtype}) differ in dtype; convert both to uint8.")
    if tuple(topview.shape) != top_a.shape[:2]:
        raise AnalysisError(f"images are {top_a.shape[:2]} px but the top view is {topview.shape}; use the TopView the images were made with.")
    return top_a, ref_a


def _all_metrics(h_top, h_ref, considered, threshold: float, tile_mm2: float, printed: float) -> dict[str, MetricScore]:
    """Every measure of Table 2 on the considered blocks at ``threshold`` (before the region-size filter)."""
    out = {}
    for name, sim in similarity_all(h_top, h_ref, METRIC_NAMES).items():
        a = considered & (sim < threshold)
        out[name] = MetricScore(anomaly_ratio=anomaly_ratio(int(a.sum()), tile_mm2, printed), n_anomalous=int(a.sum()),
                                mean_similarity=float(sim[considered].mean()) if considered.any() else 1.0)
    return out


def analyze_layer(
    top: np.ndarray,
    reference: np.ndarray,
    footprint: np.ndarray,
    topview: TopView,
    settings: AnalysisSettings | None = None,
    *,
    valid: np.ndarray | None = None,
    layer: int = 0,
    z: float = 0.0,
    all_metrics: bool = False,
    ref_hog: tuple[np.ndarray, np.ndarray] | None = None,
    off_colour: np.ndarray | None = None,
) -> LayerResult:
    """Compare the photo's top view with the reference of one layer.

    Parameters
    ----------
    top : ndarray, shape (H, W) or (H, W, 3)
        Photo warped to the top view (uint8, uint16 or float 0-1).
    reference : ndarray, shape (H, W) or (H, W, 3), same dtype as ``top``
        Rendered ideal layer.
    footprint : ndarray, shape (H, W), bool
        Pixels where this layer is printed.
    topview : TopView
        Geometry of the images; ``topview.shape`` must be ``(H, W)``.
    settings : AnalysisSettings, optional
        Metric, threshold T_S, HOG parameters, margin (defaults: paper's).
    valid : ndarray, shape (H, W), bool, optional
        Pixels the camera saw (from the warp); all pixels when omitted.
    layer, z : int, float
        Layer index and height (mm), copied into the result.
    all_metrics : bool
        Also score every measure of Table 2 into ``result.per_metric``
        (``{name: MetricScore}``, same blocks and threshold, before the
        ``min_region_blocks`` filter).
    ref_hog : (ndarray, ndarray), optional
        :func:`reference_hog` of ``reference`` with the same ``settings``
        (computed ahead with the reference); computed here when omitted.
    off_colour : ndarray, bool, shape (N, M), optional
        Blocks whose tile is another material than the part's filament
        (:func:`~layerwatch.analysis.part_colour.off_colour_blocks`): their
        similarity is taken as at most ``threshold / 2`` and they are considered
        (they lie on the part, in its footprint or its own gaps), so they are
        anomalous blocks of eq. (5) and of the regions like those the HOG test found.

    Returns
    -------
    LayerResult
        ``heatmap`` (N, M) float32 similarities, ``mask`` (N, M) considered
        blocks, a% (eq. 5), areas in mm^2, regions in bed mm (largest first),
        ``timings_ms`` (``hog``, ``metric``, ``regions``, ``total``),
        ``grid``, ``similarity_mean``/``similarity_min`` and ``shown_blocks``
        (when hysteresis grew the drawn regions).
        ``status`` is ``"skipped"`` when no printed pixel is visible.

    Raises
    ------
    AnalysisError
        Size/dtype mismatch, NaN pixels, mask shape mismatch, image too small, ``off_colour`` not of the
        block grid's shape.

    References
    ----------
    Petsiuk & Pearce (2022), eqs. (4)-(5).
    """
    t0 = time.perf_counter()
    st = settings or AnalysisSettings()
    top_a, ref_a = _check_images(top, reference, topview)
    foot = _mask(footprint, top_a.shape[:2], "footprint")
    seen = None if valid is None else _mask(valid, top_a.shape[:2], "valid")
    h_top, h_ref = block_hogs(top_a, ref_a, st, ref_hog)
    t1 = time.perf_counter()
    heat = similarity(h_top, h_ref, st.metric)
    if off_colour is not None:
        if np.shape(off_colour) != heat.shape:
            raise AnalysisError(f"off-colour blocks {np.shape(off_colour)} do not fit the {heat.shape} block grid.")
        heat = np.where(off_colour, np.minimum(heat, np.float32(0.5 * st.threshold)), heat).astype(heat.dtype)
    t2 = time.perf_counter()
    res = _layer_result(heat, foot, seen, topview, st, off_colour)
    res.layer, res.z = int(layer), float(z)
    t3 = time.perf_counter()
    if all_metrics:
        tile_mm2 = (st.cell_px / topview.px_per_mm) ** 2
        res.per_metric = _all_metrics(h_top, h_ref, res.mask, st.threshold, tile_mm2, res.printed_area_mm2)
    t4 = time.perf_counter()
    res.timings_ms = {
        "hog": (t1 - t0) * 1e3, "metric": (t2 - t1) * 1e3, "regions": (t3 - t2) * 1e3,
        "total": (t4 - t0) * 1e3,
    }
    return res


def _layer_result(heat: np.ndarray, foot: np.ndarray, seen: np.ndarray | None, topview: TopView,
                  st: AnalysisSettings, also_considered: np.ndarray | None = None) -> LayerResult:
    """Considered blocks, anomalous blocks and regions, areas and a% (eq. 5) of one similarity map.

    ``heat`` (N, M) similarities, ``foot`` (H, W) footprint, ``seen`` (H, W) pixels the camera saw
    (``None``: all), ``also_considered`` (N, M) blocks considered besides those near the footprint
    (the off-colour blocks). The record's ``layer``/``z`` are left for the caller.
    """
    c, b = st.cell_px, st.block_cells
    n, m = heat.shape
    foot_int = _integral(foot)
    considered = near_footprint(foot, heat.shape, topview, st, st.footprint_margin_mm, seen, foot_int)
    if also_considered is not None:
        considered = considered | also_considered
    foot_frac = tile_share(foot, heat.shape, c, b, foot_int)
    grid = {"cell_px": c, "block_cells": b, "min_region_blocks": st.min_region_blocks}
    anom, regions = _regions(considered & (heat < st.threshold), heat, foot_frac, grid, topview)
    shown = anom  # what the overlay draws: grown by hysteresis when asked (regions and a% are not)
    if st.grow_threshold > 0 and anom.any():
        reach = growth_reach(considered, foot, topview, st, seen, foot_int)
        shown = grow_regions(anom, reach & (heat < st.threshold + st.grow_threshold))
    tile_mm2 = (c / topview.px_per_mm) ** 2
    n_printed = int(foot_int[-1, -1]) if seen is None else int(np.count_nonzero(foot & seen))
    printed = n_printed / topview.px_per_mm**2
    # what each anomalous block adds to S_A: its whole tile (the paper) or the part's share of it
    n_counted = float(area_weight(foot_frac, c / topview.px_per_mm, st.anomalous_area)[anom].sum())
    n_anom = int(anom.sum())
    res = LayerResult(
        layer=0, z=0.0, metric=st.metric, threshold=float(st.threshold),
        anomaly_ratio=anomaly_ratio(n_counted, tile_mm2, printed),
        printed_area_mm2=printed, anomalous_area_mm2=n_counted * tile_mm2,
        uncounted_mm2=max(n_anom - n_counted, 0.0) * tile_mm2,
        outside_area_mm2=float((1.0 - foot_frac[anom]).sum()) * tile_mm2,
        n_blocks=int(considered.sum()), n_anomalous=n_anom, regions=regions,
        heatmap=heat, mask=considered,
        grid=BlockGrid(cell_px=c, block_cells=b, min_region_blocks=st.min_region_blocks,
                       **block_geometry(c, b, topview.px_per_mm)),
    )
    if printed == 0 or not considered.any():
        res.status = "skipped"
        res.message = "no printed area of this layer is visible in the top view"
    vals = heat[considered]
    res.similarity_mean = float(vals.mean()) if vals.size else 1.0
    res.similarity_min = float(vals.min()) if vals.size else 1.0
    if shown is not anom:
        res.shown_blocks = np.flatnonzero(shown).tolist()  # flat (N, M) indices, for the overlay
    return res
