"""Small synthetic toolpaths for tests and demos (no slicer needed)."""

from __future__ import annotations

from typing import Any

import numpy as np

from layerwatch.errors import ConfigError
from layerwatch.gcode.toolpath import FEATURES, Toolpath

__all__ = ["blocks_part", "box_part", "tower_part", "toolpath_gcode", "window_part"]


def _loop(x0, y0, x1, y1):
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    return c, np.roll(c, -1, axis=0)


def box_part(
    size_mm: float = 30.0,
    height_mm: float = 6.0,
    layer_h: float = 0.3,
    center: tuple[float, float] = (0.0, 0.0),
    width: float = 0.45,
    fin: bool = True,
) -> Toolpath:
    """A square block with two perimeters and alternating +-45 deg infill, plus a thin fin.

    Parameters
    ----------
    size_mm : float
        Side of the block, mm.
    height_mm, layer_h : float
        Print height and layer height, mm.
    center : (float, float)
        Block centre on the bed, mm.
    width : float
        Bead width, mm.
    fin : bool
        Add a 2-perimeter-thick (~0.9 mm) wall 12 mm long beside the block.

    Returns
    -------
    Toolpath
        Features: external_perimeter, perimeter, infill.
    """
    cx, cy = center
    h = size_mm / 2
    starts, ends, feats = [], [], []
    zs: list[float] = []
    ext, per, inf = (FEATURES.index(n) for n in ("external_perimeter", "perimeter", "infill"))
    n_layers = int(round(height_mm / layer_h))
    for k in range(n_layers):
        z = round((k + 1) * layer_h, 6)
        for off, code in ((0.0, ext), (width, per)):
            a, b = _loop(cx - h + off, cy - h + off, cx + h - off, cy + h - off)
            starts.append(a)
            ends.append(b)
            feats += [code] * 4
        # infill: lines at +-45 deg clipped to the inner square
        inner = h - 2 * width
        sp = 2 * width
        sgn = 1 if k % 2 == 0 else -1
        for c in np.arange(-2 * inner + sp / 2, 2 * inner, sp):
            # line x - sgn*y = c, within |x|,|y| <= inner
            ys = np.array([-inner, inner])
            xs = c + sgn * ys
            xs = np.clip(xs, -inner, inner)
            ys = (xs - c) * sgn
            if np.hypot(*(np.diff(xs), np.diff(ys))) < width:
                continue
            starts.append([[cx + xs[0], cy + ys[0]]])
            ends.append([[cx + xs[1], cy + ys[1]]])
            feats.append(inf)
        if fin:
            x0 = cx + h + 6.0
            a, b = _loop(x0, cy - 6.0, x0 + width, cy + 6.0)
            starts.append(a)
            ends.append(b)
            feats += [ext] * 4
        zs += [z] * (sum(len(s) for s in starts) - len(zs))
    return Toolpath.from_segments(
        np.concatenate(starts), np.concatenate(ends), np.array(zs), width=width,
        feature=np.array(feats, np.uint8), layer_height=layer_h, source="<box_part>",
    )


def _ring(cx, cy, r, n=48):
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    c = np.c_[cx + r * np.cos(a), cy + r * np.sin(a)]
    return c, np.roll(c, -1, axis=0)


def _clip_line(p0, d, half, r_in, r_out):
    """Parameter intervals ``[t0, t1]`` of the line ``p0 + t*d`` (``|d| = 1``, centre-relative) that lie in the
    square ``|x|, |y| <= half``, outside the circle ``r_in`` and (if ``r_out``) inside the circle ``r_out``."""
    lo, hi = -np.inf, np.inf
    for k in range(2):
        if abs(d[k]) < 1e-12:
            if abs(p0[k]) > half:
                return []
            continue
        t0, t1 = sorted(((-half - p0[k]) / d[k], (half - p0[k]) / d[k]))
        lo, hi = max(lo, t0), min(hi, t1)
    tc = -float(p0 @ d)  # closest approach to the centre
    dist2 = float(p0 @ p0) - tc * tc
    if r_out is not None:
        if dist2 >= r_out**2:
            return []
        w = np.sqrt(r_out**2 - dist2)
        lo, hi = max(lo, tc - w), min(hi, tc + w)
    if lo >= hi:
        return []
    if dist2 >= r_in**2:
        return [(lo, hi)]
    w = np.sqrt(r_in**2 - dist2)
    return [(a, b) for a, b in ((lo, min(hi, tc - w)), (max(lo, tc + w), hi)) if b > a]


def _tower_walls(center, h, r_hole, r_boss, width, block, ext, per):
    """``[((starts, ends), feature code)]``: outer and inner perimeter around the hole and
    around the outside (the square block while ``block``, else the round boss)."""
    cx, cy = center
    loops = [(_ring(cx, cy, r_hole + width / 2), ext), (_ring(cx, cy, r_hole + 1.5 * width), per)]
    if block:
        loops += [(_loop(cx - h + width / 2, cy - h + width / 2, cx + h - width / 2, cy + h - width / 2), ext),
                  (_loop(cx - h + 1.5 * width, cy - h + 1.5 * width, cx + h - 1.5 * width, cy + h - 1.5 * width), per)]
    else:
        loops += [(_ring(cx, cy, r_boss - width / 2, 64), ext), (_ring(cx, cy, r_boss - 1.5 * width, 64), per)]
    return loops


def _tower_infill(center, k, half, r_in, r_out, spacing, width):
    """``[(start, end)]`` of layer ``k``'s infill lines (+-45 deg alternating, ``spacing`` mm
    apart) clipped as :func:`_clip_line` says; lines shorter than ``width`` are dropped."""
    cx, cy = center
    d = np.array([1.0, 1.0 if k % 2 == 0 else -1.0]) / np.sqrt(2.0)
    nrm = np.array([-d[1], d[0]])
    lines = []
    for c in np.arange(-np.sqrt(2) * half + spacing / 2, np.sqrt(2) * half, spacing):
        p0 = c * nrm
        for t0, t1 in _clip_line(p0, d, half, r_in, r_out):
            if t1 - t0 < width:
                continue
            lines.append(([[cx, cy] + p0 + t0 * d], [[cx, cy] + p0 + t1 * d]))
    return lines


def tower_part(
    size_mm: float = 30.0,
    height_mm: float = 100.0,
    layer_h: float = 0.2,
    center: tuple[float, float] = (0.0, 0.0),
    hole_mm: float = 10.0,
    boss_mm: float = 18.0,
    boss_from_mm: float = 70.0,
    infill_spacing_mm: float = 2.0,
    width: float = 0.45,
    solid_layers: int = 0,
) -> Toolpath:
    """A tall part: a square block with a round through-hole, topped by a round boss (a tube) around the hole.

    Every layer has an outer and an inner perimeter around the outside and
    around the hole, and sparse rectilinear infill (alternating +-45 deg,
    ``infill_spacing_mm`` apart) clipped between them; at ``boss_from_mm``
    the footprint shrinks from the square block to the boss's ring, so the
    block's top stays in view beside the boss. With ``solid_layers`` > 0 the
    bottom and top ``solid_layers`` layers of the block and of the boss are
    solid infill (lines one bead width apart), as a slicer prints them;
    with 0 the block's top is sparse infill seen from above.

    Parameters
    ----------
    size_mm : float
        Side of the square block, mm.
    height_mm, layer_h : float
        Print height and layer height, mm (100 mm at 0.2 mm = 500 layers).
    center : (float, float)
        Part centre on the bed, mm.
    hole_mm, boss_mm : float
        Diameters of the through-hole and of the boss, mm.
    boss_from_mm : float
        Height where the block ends and the boss begins, mm.
    infill_spacing_mm : float
        Distance between infill lines, mm (2 mm at 0.45 mm beads ~ 22 % infill).
    width : float
        Bead width, mm.
    solid_layers : int
        Solid bottom/top layers of the block and of the boss.

    Returns
    -------
    Toolpath
        Features: external_perimeter, perimeter, infill, solid_infill, top_solid_infill.
    """
    cx, cy = center
    h = size_mm / 2
    r_hole, r_boss = hole_mm / 2, boss_mm / 2
    ext, per, inf, sol, top = (FEATURES.index(n) for n in ("external_perimeter", "perimeter", "infill",
                                                          "solid_infill", "top_solid_infill"))
    n_block = int(round(boss_from_mm / layer_h))
    starts, ends, feats = [], [], []
    zs: list[float] = []
    n_layers = int(round(height_mm / layer_h))
    for k in range(n_layers):
        z = round((k + 1) * layer_h, 6)
        block = z <= boss_from_mm + 1e-9
        for (a, b), code in _tower_walls(center, h, r_hole, r_boss, width, block, ext, per):
            starts.append(a)
            ends.append(b)
            feats += [code] * len(a)
        half = h - 2 * width if block else r_boss
        r_out = None if block else r_boss - 2 * width
        first, last = (0, n_block - 1) if block else (n_block, n_layers - 1)
        spacing, code = infill_spacing_mm, inf
        if k < first + solid_layers or k > last - solid_layers:
            spacing, code = width, (top if k > last - solid_layers else sol)
        for a, b in _tower_infill(center, k, half, r_hole + 2 * width, r_out, spacing, width):
            starts.append(a)
            ends.append(b)
            feats.append(code)
        zs += [z] * (sum(len(s) for s in starts) - len(zs))
    return Toolpath.from_segments(
        np.concatenate(starts), np.concatenate(ends), np.array(zs), width=width,
        feature=np.array(feats, np.uint8), layer_height=layer_h, source="<tower_part>",
    )


def _block_layer(x0, y0, x1, y1, width, along_x):
    """One layer of a solid block: a perimeter loop and rectilinear solid infill, (starts, ends, features)."""
    ext, sol = FEATURES.index("external_perimeter"), FEATURES.index("solid_infill")
    a, b = _loop(x0 + width / 2, y0 + width / 2, x1 - width / 2, y1 - width / 2)
    starts, ends, feats = [a], [b], [ext] * 4
    lo, hi = (y0 + width, y1 - width) if along_x else (x0 + width, x1 - width)
    s0, s1 = (x0 + width, x1 - width) if along_x else (y0 + width, y1 - width)
    if hi >= lo and s1 - s0 >= width:
        for c in np.arange(lo + (hi - lo) % width / 2, hi + 1e-9, width):
            p, q = ([s0, c], [s1, c]) if along_x else ([c, s0], [c, s1])
            starts.append([p])
            ends.append([q])
            feats.append(sol)
    return starts, ends, feats


def blocks_part(
    blocks,
    layer_h: float = 0.2,
    width: float = 0.45,
    center: tuple[float, float] = (0.0, 0.0),
    source: str = "<blocks_part>",
) -> Toolpath:
    """A part built from solid axis-aligned blocks, each printed wherever its height range covers a layer.

    Every layer prints each block whose ``(z0, z1]`` contains the layer's
    top: a perimeter loop and solid rectilinear infill (along X on even
    layers, along Y on odd ones). A block over empty space is an overhang or
    a bridge, a gap between blocks of one wall a window: the layers are
    printed as given, nothing is supported.

    Parameters
    ----------
    blocks : sequence of (x0, y0, x1, y1, z0, z1)
        Blocks relative to ``center``, mm (``x0 < x1``, ``y0 < y1``, ``0 <= z0 < z1``).
    layer_h, width : float
        Layer height and bead width, mm.
    center : (float, float)
        Offset of the part on the bed, mm.
    source : str
        The toolpath's ``source``.

    Returns
    -------
    Toolpath
        Features: external_perimeter, solid_infill.

    Raises
    ------
    ConfigError
        No block, or a block that is empty or not finite.
    """
    bl = np.asarray(blocks, np.float64).reshape(-1, 6)
    ok = np.isfinite(bl).all(1) & (bl[:, 0] < bl[:, 2]) & (bl[:, 1] < bl[:, 3]) & (bl[:, 4] >= 0) & (bl[:, 4] < bl[:, 5])
    if len(bl) == 0 or not ok.all() or not (layer_h > 0 and width > 0):
        raise ConfigError("blocks_part needs blocks (x0, y0, x1, y1, z0, z1) with x0 < x1, y0 < y1, 0 <= z0 < z1 "
                          "and a positive layer height and width.")
    cx, cy = center
    starts: list[Any] = []
    ends: list[Any] = []
    zs: list[float] = []
    feats: list[int] = []
    n_layers = int(round(bl[:, 5].max() / layer_h))
    for k in range(n_layers):
        z = round((k + 1) * layer_h, 6)
        for x0, y0, x1, y1, z0, z1 in bl:
            if z0 + 1e-6 < z <= z1 + 1e-6:
                s, e, f = _block_layer(cx + x0, cy + y0, cx + x1, cy + y1, width, k % 2 == 0)
                starts += s
                ends += e
                feats += f
        zs += [z] * (sum(len(s) for s in starts) - len(zs))
    return Toolpath.from_segments(
        np.concatenate(starts), np.concatenate(ends), np.array(zs), width=width,
        feature=np.array(feats, np.uint8), layer_height=layer_h, source=source,
    )


def window_part(center: tuple[float, float] = (0.0, 0.0), layer_h: float = 0.2, width: float = 0.45) -> Toolpath:
    """A part a height map cannot hold: a hollow box with a window, a bridge and an overhang, 46 x 16 x 14 mm.

    Seen from a camera in front of the printer (-Y), left to right:

    * a **bridge**: two 4 x 6 mm pillars 8 mm apart, 8 mm tall, spanned by a
      2 mm deck (the camera sees the bed and the far side under it);
    * a **hollow box** 20 x 16 mm, 14 mm tall, 1.8 mm walls on a 1 mm floor,
      with an 8 x 5 mm **window** through its front wall from 5 to 10 mm (the
      camera sees the floor and the back wall inside through it);
    * an **overhang**: a 4 x 6 mm column 12 mm tall with a 6 mm ledge sticking
      out towards the camera from 7 to 9 mm (the bed and the column under it).

    Parameters
    ----------
    center : (float, float)
        Offset of the part on the bed, mm (the part spans x -23..23, y -8..8 around it).
    layer_h, width : float
        Layer height and bead width, mm.

    Returns
    -------
    Toolpath
    """
    t = 1.8
    blocks = [
        (-23, -3, -19, 3, 0, 8), (-11, -3, -7, 3, 0, 8), (-23, -3, -7, 3, 8, 10),  # bridge
        (-5, -8, 15, 8, 0, 1),  # box: floor
        (-5, 8 - t, 15, 8, 1, 14), (-5, -8 + t, -5 + t, 8 - t, 1, 14), (15 - t, -8 + t, 15, 8 - t, 1, 14),
        (-5, -8, 15, -8 + t, 1, 5), (-5, -8, 1, -8 + t, 5, 10), (9, -8, 15, -8 + t, 5, 10),  # front, window
        (-5, -8, 15, -8 + t, 10, 14),
        (19, -2, 23, 4, 0, 12), (19, -8, 23, -2, 7, 9),  # column and ledge
    ]
    return blocks_part(blocks, layer_h, width, center, source="<window_part>")


_TYPE_NAMES = {"external_perimeter": "External perimeter", "perimeter": "Perimeter", "infill": "Internal infill",
               "solid_infill": "Solid infill", "top_solid_infill": "Top solid infill"}


def toolpath_gcode(toolpath: Toolpath, filament_diameter: float = 1.75, feed_mm_min: float = 2400.0) -> bytes:
    """PrusaSlicer-style G-code of a synthetic toolpath, for the virtual printer and ``insert_snapshots``.

    Layers are tagged ``;LAYER_CHANGE`` / ``;Z:`` / ``;HEIGHT:``, features
    ``;TYPE:``; extrusion is relative (``M83``), ``E`` = bead cross-section
    (rounded rectangle, ``(w - h) h + pi h^2 / 4``) x length / filament area; travels are ``G0``
    moves without extrusion. :func:`layerwatch.gcode.read_toolpath` reads the
    same layers, segments and features back.

    Parameters
    ----------
    toolpath : Toolpath
        E.g. from :func:`tower_part` or :func:`box_part`.
    filament_diameter : float
        mm.
    feed_mm_min : float
        Print feed rate, mm/min.

    Returns
    -------
    bytes
        ASCII G-code.
    """
    area = np.pi * (filament_diameter / 2) ** 2
    out = ["; generated by layerwatch.simulate.parts.toolpath_gcode", f"; filament_diameter = {filament_diameter}",
           "G21", "G90", "M83", "G28"]
    prev_z = 0.0
    for lay in toolpath.layers:
        sl = slice(lay.seg_start, lay.seg_stop)
        z = float(lay.z)
        lh = max(z - prev_z, 0.05)
        out += [";LAYER_CHANGE", f";Z:{z:.3f}", f";HEIGHT:{lh:.3f}", f"G1 Z{z:.3f} F720"]
        pos, feat = None, None
        for a, b, w, f in zip(toolpath.start[sl], toolpath.end[sl], toolpath.width[sl], toolpath.feature[sl],
                              strict=True):
            if pos is None or np.hypot(*(a - pos)) > 1e-6:
                out.append(f"G0 X{a[0]:.3f} Y{a[1]:.3f} F9000")
            if f != feat:
                out.append(f";TYPE:{_TYPE_NAMES.get(FEATURES[f], 'Internal infill')}")
                feat = f
            e = float(np.hypot(*(b - a))) * ((float(w) - lh) * lh + np.pi * lh * lh / 4) / area
            out.append(f"G1 X{b[0]:.3f} Y{b[1]:.3f} E{e:.5f} F{feed_mm_min:.0f}")
            pos = b
        prev_z = z
    out += ["M107", "M84", ""]
    return "\n".join(out).encode()
