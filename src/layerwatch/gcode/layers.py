"""Layer detection: slicer tags first, else the Z of extruding moves.

Travel-only Z changes (Z-hops) never start a layer because only extruding
segments are looked at. Vase/spiral prints (Z rising on almost every
segment) are binned on the layer height.
"""

from __future__ import annotations

import numpy as np

__all__ = ["assign_layers"]


def _runs(ids: np.ndarray) -> np.ndarray:
    """Start indices of runs of equal ``ids`` plus the end, shape (L+1,)."""
    n = ids.shape[0]
    if n == 0:
        return np.zeros(1, np.int64)
    cuts = np.flatnonzero(ids[1:] != ids[:-1]) + 1
    return np.concatenate([[0], cuts, [n]]).astype(np.int64)


def _revolution_height(xy: np.ndarray, z: np.ndarray) -> float | None:
    """Z rise per turn around the print's centroid (spiral layer height), mm."""
    c = xy.mean(axis=0)
    theta = np.unwrap(np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0]))
    turns = abs(theta[-1] - theta[0]) / (2 * np.pi)
    rise = float(z[-1] - z[0])
    return rise / turns if turns >= 1 and rise > 0 else None


def assign_layers(
    seg_z: np.ndarray,
    seg_line: np.ndarray,
    tag_lines: np.ndarray,
    tag_z: np.ndarray,
    style: str | None,
    layer_height_hint: float | None = None,
    seg_xy: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, str, list[str]]:
    """Split the segment list into layers.

    Parameters
    ----------
    seg_z : ndarray, shape (S,), float64
        Z of each extruding segment, mm.
    seg_line : ndarray, shape (S,), int64
        Source line of each segment (non-decreasing).
    tag_lines, tag_z : ndarray, shape (T,)
        Lines of the slicer's layer tags and the Z they name (NaN if none).
    style : str or None
        Tag style name, ``None`` when the file has no layer tags.
    layer_height_hint : float, optional
        Layer height from the file header, used for spiral binning.
    seg_xy : ndarray, shape (S, 2), optional
        Segment end points; a spiral's height per turn when nothing else says.

    Returns
    -------
    bounds : ndarray, shape (L+1,), int64
        Segment index where each layer starts, then ``S``.
    z : ndarray, shape (L,), float64
        Z of each layer's top, mm.
    detection : str
        ``"tags:<style>"``, ``"z"`` or ``"spiral"``.
    warnings : list of str
    """
    warnings: list[str] = []
    n = seg_z.shape[0]
    if n == 0:
        return np.zeros(1, np.int64), np.zeros(0), "none", warnings
    if style is not None and tag_lines.size:
        bounds, z = _tag_layers(seg_z, seg_line, tag_lines, tag_z)
        return bounds, z, f"tags:{style}", warnings
    dz = np.abs(np.diff(seg_z))
    changes = int(np.count_nonzero(dz > 1e-4))
    if n > 50 and changes > 0.3 * n:
        h = _spiral_height(seg_z, layer_height_hint, seg_xy, warnings)
        bounds, z = _spiral_layers(seg_z, h)
        return bounds, z, "spiral", warnings
    bounds, z = _z_layers(seg_z)
    return bounds, z, "z", warnings


def _tag_layers(
    seg_z: np.ndarray, seg_line: np.ndarray, tag_lines: np.ndarray, tag_z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Layers from the slicer's layer tags: ``(bounds, z)`` as :func:`assign_layers` returns.

    A segment belongs to the last tag at or above its line; moves before the first tag
    (purge line) join layer 0. ``seg_line`` is sorted, so each tag's first segment is one
    binary search (T of them, not S).
    """
    n = seg_z.shape[0]
    starts = np.searchsorted(seg_line, tag_lines[1:], side="left")
    cuts = starts[(starts > 0) & (starts < n)]
    bounds = np.unique(np.concatenate([[0], cuts, [n]])).astype(np.int64)
    ids = np.maximum(np.searchsorted(tag_lines, seg_line[bounds[:-1]], side="right") - 1, 0)
    z = tag_z[ids].astype(np.float64)
    mid = seg_z[(bounds[:-1] + bounds[1:]) // 2]  # mid-layer segment where the tag names no Z
    return bounds, np.where(np.isfinite(z), z, mid)


def _spiral_height(
    seg_z: np.ndarray, layer_height_hint: float | None, seg_xy: np.ndarray | None, warnings: list[str]
) -> float:
    """Bin height of a spiral print, mm: the header's layer height, else the step between its
    flat stretches, else its rise per turn, else 0.2 mm (or the whole rise) with a warning."""
    h = layer_height_hint
    plateau = _runs(np.round(seg_z, 4))
    sizes = np.diff(plateau)
    flat_z = seg_z[plateau[:-1][sizes >= 10]]
    steps = np.diff(np.unique(flat_z))
    if h is None and steps.size:
        h = float(np.median(steps))
    if h is None and seg_xy is not None:
        h = _revolution_height(seg_xy, seg_z)
    if h is None or not (0.01 <= h <= 2.0):
        rise = float(seg_z.max() - seg_z.min())
        h = 0.2 if rise <= 0 else min(0.2, rise)
        warnings.append(f"spiral print without a known layer height; binned every {h:g} mm")
    return h


def _spiral_layers(seg_z: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """A spiral print binned every ``h`` mm: ``(bounds, z)`` as :func:`assign_layers` returns."""
    n = seg_z.shape[0]
    # base one step below the first segment: its own layer top is z0 (flat start) or the
    # first segment ends a rising turn that began one increment lower
    d0 = float(seg_z[1] - seg_z[0]) if n > 1 else 0.0
    zb = float(seg_z[0]) - (d0 if 1e-6 < d0 < h else h)
    k = np.ceil((seg_z - zb) / h - 1e-6).astype(np.int64)
    k = np.maximum.accumulate(np.maximum(k, 1))
    bounds = _runs(k)
    z = zb + k[bounds[:-1]] * h
    return bounds, z


def _z_layers(seg_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Layers where the extruding Z changes: ``(bounds, z)`` as :func:`assign_layers` returns."""
    n = seg_z.shape[0]
    bounds = _runs(np.round(seg_z, 4))
    z = seg_z[bounds[:-1]].astype(np.float64)
    # a prime/purge line drawn above the first layer (IceSL, start G-code) joins layer 0
    while z.size >= 2 and z[0] > z[1] + 1e-4 and bounds[1] < 0.05 * n:
        bounds = np.delete(bounds, 1)
        z = z[1:]
    return bounds, z
