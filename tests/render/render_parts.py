"""Synthetic toolpaths for tests and benchmarks (no slicer needed).

All parts are built with :meth:`Toolpath.from_segments`: perimeters as closed
polygons inset by one bead width each, infill as parallel lines at +-45
degrees alternating per layer, clipped to the innermost perimeter.
"""

from __future__ import annotations

import numpy as np

from layerwatch.gcode.toolpath import Toolpath, feature_code

__all__ = ["square_layer_segments", "square_part", "thin_wall_part", "dense_layer"]


def _rect_loop(cx: float, cy: float, half: float) -> tuple[np.ndarray, np.ndarray]:
    c = np.array(
        [[cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half], [cx - half, cy + half]]
    )
    return c, np.roll(c, -1, axis=0)


def _diagonal_lines(cx, cy, half, spacing, angle_sign):
    """Lines at +-45 deg filling the square |x-cx|,|y-cy| <= half, shape (L, 2) x2."""
    # lines x - s*y = c  (s = +1 for +45 deg); clip to the square
    s = 1.0 if angle_sign > 0 else -1.0
    step = spacing * np.sqrt(2.0)
    cs = np.arange(-2 * half + step / 2, 2 * half, step)
    starts, ends = [], []
    for c in cs:
        # y range where x = c + s*y stays inside [-half, half]
        if s > 0:
            ylo, yhi = max(-half, -half - c), min(half, half - c)
        else:
            ylo, yhi = max(-half, c - half), min(half, c + half)
        if yhi - ylo < 1e-6:
            continue
        a = np.array([c + s * ylo + cx, ylo + cy])
        b = np.array([c + s * yhi + cx, yhi + cy])
        starts.append(a)
        ends.append(b)
    return np.array(starts).reshape(-1, 2), np.array(ends).reshape(-1, 2)


def square_layer_segments(
    center=(0.0, 0.0), size: float = 20.0, width: float = 0.45, perimeters: int = 2,
    infill_spacing: float | None = None, angle_sign: int = 1,
):
    """One layer of a square part: perimeters plus diagonal infill.

    Returns
    -------
    start, end : ndarray, shape (S, 2), float64
        Segment endpoints, mm.
    feature : ndarray, shape (S,), uint8
    """
    cx, cy = center
    starts, ends, feats = [], [], []
    for k in range(perimeters):
        half = size / 2 - width / 2 - k * width
        a, b = _rect_loop(cx, cy, half)
        starts.append(a)
        ends.append(b)
        code = feature_code("external_perimeter" if k == 0 else "perimeter")
        feats.append(np.full(4, code, np.uint8))
    inner = size / 2 - perimeters * width
    a, b = _diagonal_lines(cx, cy, inner - width / 2, infill_spacing or width, angle_sign)
    starts.append(a)
    ends.append(b)
    feats.append(np.full(len(a), feature_code("solid_infill"), np.uint8))
    return np.concatenate(starts), np.concatenate(ends), np.concatenate(feats)


def square_part(
    n_layers: int = 5, center=(0.0, 0.0), size: float = 20.0, width: float = 0.45,
    layer_height: float = 0.3, infill_spacing: float | None = None,
) -> Toolpath:
    """A solid square block: each layer perimeters + diagonal infill alternating +-45 deg."""
    S, E, Z, F = [], [], [], []
    for i in range(n_layers):
        s, e, f = square_layer_segments(center, size, width, 2, infill_spacing, 1 if i % 2 == 0 else -1)
        S.append(s)
        E.append(e)
        F.append(f)
        Z.append(np.full(len(s), layer_height * (i + 1)))
    return Toolpath.from_segments(
        np.concatenate(S), np.concatenate(E), np.concatenate(Z), width, feature=np.concatenate(F),
        layer_height=layer_height, source="<square part>",
    )


def thin_wall_part(
    n_layers: int = 4, center=(0.0, 0.0), length: float = 30.0, width: float = 0.45,
    layer_height: float = 0.2,
) -> Toolpath:
    """A single-bead wall along X (one segment per layer)."""
    cx, cy = center
    s = np.tile([[cx - length / 2, cy]], (n_layers, 1))
    e = np.tile([[cx + length / 2, cy]], (n_layers, 1))
    z = layer_height * (np.arange(n_layers) + 1)
    return Toolpath.from_segments(s, e, z, width, layer_height=layer_height, source="<thin wall>")


def dense_layer(
    n_segments: int = 20_000, center=(0.0, 0.0), size: float = 85.0, width: float = 0.45,
    z: float = 0.3,
) -> Toolpath:
    """One layer of about ``n_segments`` short segments: zig-zag dense infill over a square.

    Lines at 45 deg with spacing ``width`` are cut into equal pieces so the
    total is ``n_segments`` (the benchmark layer of issue 6).
    """
    a, b = _diagonal_lines(center[0], center[1], size / 2, width, 1)
    lengths = np.linalg.norm(b - a, axis=1)
    per_mm = n_segments / lengths.sum()
    pieces = np.maximum(1, np.round(lengths * per_mm).astype(int))
    S, E = [], []
    for p, q, k in zip(a, b, pieces, strict=True):
        t = np.linspace(0.0, 1.0, k + 1)[:, None]
        pts = p + t * (q - p)
        S.append(pts[:-1])
        E.append(pts[1:])
    S, E = np.concatenate(S), np.concatenate(E)
    return Toolpath.from_segments(S, E, np.full(len(S), z), width, layer_height=z, source="<dense layer>")
