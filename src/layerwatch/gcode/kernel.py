"""Numba state machine: G-code bytes -> extruding segments, in one pass.

The kernel lexes the ``uint8`` buffer (no ``str`` copy) and runs the modal
machine as it goes (G90/G91, M82/M83, G92, G20/G21, G0-G3, G10/G11, G28,
T, F, M101/M103). It emits flat arrays of extruding segments, the lines of
travel moves, the byte offsets of ``;`` comments that may be slicer tags
(decoded in Python by :mod:`layerwatch.gcode.tags`) and, for the
post-processor, the modal state at requested "probe" lines.

Conventions: ``phys = logical + offset`` per axis (G92 changes the offset),
positions in mm (G20 scales by 25.4), E relative when ``M83`` or ``G91``
(Klipper/Marlin semantics: G91 makes E relative too; G90 keeps M83).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from layerwatch.gcode.arcs import arc_geometry

# stats slots
ST_LINES, ST_SEG, ST_TRAVEL, ST_CMT, ST_BAD, ST_FIRST_BAD, ST_UNKNOWN, ST_ABSURD = 0, 1, 2, 3, 4, 5, 6, 7
ST_FIRST_ABSURD, ST_TOOLON, ST_ARCS, ST_ARC_BAD, ST_FIRST_ARC_BAD, ST_NONL, ST_FWRETRACT = 8, 9, 10, 11, 12, 13, 14
N_STATS = 16
#: probe state columns: logical x, y, z, offsets x, y, z, e, feed (mm/min), abs_xyz, e_rel_flag, tool, inch,
#: tool-on (M101 dialect, 1 when the extruder is switched on)
N_PROBE = 13
ABSURD_MM = 1.0e5
#: first characters of ';' comments worth handing to the tag decoder
_TAG_FIRST = np.zeros(256, np.bool_)
for _c in b"LlZzTtFfCcBb'Ee":
    _TAG_FIRST[_c] = True


@nb.njit(cache=True, inline="always")
def _is_digit(c):
    return 48 <= c <= 57


@nb.njit(cache=True)
def _parse_num(buf, i, n):
    """Parse a decimal number at ``buf[i:]`` (no exponent: ``E`` is an axis); returns (value, next_i, ok)."""
    while i < n and (buf[i] == 32 or buf[i] == 9):
        i += 1
    sign = 1.0
    if i < n and (buf[i] == 45 or buf[i] == 43):
        if buf[i] == 45:
            sign = -1.0
        i += 1
    val = 0.0
    nd = 0
    while i < n and _is_digit(buf[i]):
        val = val * 10.0 + (buf[i] - 48)
        i += 1
        nd += 1
    if i < n and buf[i] == 46:
        i += 1
        scale = 0.1
        while i < n and _is_digit(buf[i]):
            val += (buf[i] - 48) * scale
            scale *= 0.1
            i += 1
            nd += 1
    return sign * val, i, nd > 0


@nb.njit(cache=True)
def _grow_f(a, k):
    b = np.empty((a.shape[0] * 2 + k, a.shape[1]), a.dtype)
    b[: a.shape[0]] = a
    return b


@nb.njit(cache=True)
def _grow_1(a, k):
    b = np.empty(a.shape[0] * 2 + k, a.dtype)
    b[: a.shape[0]] = a
    return b


@nb.njit(cache=True)
def run_kernel(buf, probes, chord_tol, e_rel_init=False):  # noqa: C901 - a state machine is one big loop
    """Lex and execute ``buf``.

    Parameters
    ----------
    buf : ndarray, shape (B,), uint8
        The G-code bytes.
    probes : ndarray, shape (P,), int64
        Sorted 1-based line numbers at whose *start* the modal state is recorded.
    chord_tol : float
        Maximum chord error when linearising arcs, mm.
    e_rel_init : bool
        Start in relative-E mode (files that never say M82/M83 but assume M83).

    Returns
    -------
    seg_a, seg_b : (S, 2) float64  segment start / end XY (physical mm)
    seg_z, seg_e : (S,) float64  Z (mm) and filament (mm)
    seg_line : (S,) int64 ; seg_tool : (S,) uint8
    travel_line : (T,) int64
    cmt : (C, 2) int64  byte offset of the ';' and its line
    probe_state : (P, N_PROBE) float64
    stats : (N_STATS,) int64
    """
    n = buf.shape[0]
    # capacity: lines that start with G (arcs grow the arrays on demand)
    cap = 16
    at_start = True
    for k in range(n):
        c = buf[k]
        if c == 10:
            at_start = True
        elif at_start and c != 32 and c != 9:
            if c == 71 or c == 103:
                cap += 1
            at_start = False
    seg_a = np.empty((cap, 2), np.float64)
    seg_b = np.empty((cap, 2), np.float64)
    seg_z = np.empty(cap, np.float64)
    seg_e = np.empty(cap, np.float64)
    seg_line = np.empty(cap, np.int64)
    seg_tool = np.empty(cap, np.uint8)
    travel_line = np.empty(cap // 4 + 16, np.int64)
    cmt = np.empty((64, 2), np.int64)
    probe_state = np.full((probes.shape[0], N_PROBE), np.nan)
    stats = np.zeros(N_STATS, np.int64)
    ns = 0
    nt = 0
    nc = 0
    npb = 0
    # modal state
    lx = 0.0
    ly = 0.0
    lz = 0.0
    ox = 0.0
    oy = 0.0
    oz = 0.0
    e = 0.0
    feed = 0.0
    abs_xyz = True
    e_rel = e_rel_init
    scale = 1.0
    tool = 0
    tool_on = False
    toolon_mode = False
    motion = 1
    line = 1
    i = 0
    while i <= n:
        while npb < probes.shape[0] and probes[npb] <= line:
            if probes[npb] == line:
                probe_state[npb, 0] = lx
                probe_state[npb, 1] = ly
                probe_state[npb, 2] = lz
                probe_state[npb, 3] = ox
                probe_state[npb, 4] = oy
                probe_state[npb, 5] = oz
                probe_state[npb, 6] = e
                probe_state[npb, 7] = feed
                probe_state[npb, 8] = 1.0 if abs_xyz else 0.0
                probe_state[npb, 9] = 1.0 if e_rel else 0.0
                probe_state[npb, 10] = tool
                probe_state[npb, 11] = 1.0 if scale != 1.0 else 0.0
                probe_state[npb, 12] = 1.0 if (toolon_mode and tool_on) else 0.0
            npb += 1
        if i == n:
            break
        # ---- lex one line
        lmotion = -1
        home = False
        setpos = False
        hx = hy = hz = he = hi = hj = hr = False
        vx = vy = vz = ve = vi = vj = vr = 0.0
        first = True
        bad = False
        nonmotion = False
        while i < n and buf[i] != 10:
            c = buf[i]
            if c == 59:  # ';'
                j = i + 1
                while j < n and (buf[j] == 32 or buf[j] == 9):
                    j += 1
                if j < n and _TAG_FIRST[buf[j]]:
                    if nc >= cmt.shape[0]:
                        cmt = _grow_f(cmt, 64)
                    cmt[nc, 0] = i
                    cmt[nc, 1] = line
                    nc += 1
                while i < n and buf[i] != 10:
                    i += 1
                break
            if c == 40:  # '(' comment
                while i < n and buf[i] != 10 and buf[i] != 41:
                    i += 1
                if i < n and buf[i] == 41:
                    i += 1
                continue
            if c == 32 or c == 9 or c == 13:
                i += 1
                continue
            if c == 42:  # '*' checksum: rest of line
                while i < n and buf[i] != 10:
                    i += 1
                break
            if 97 <= c <= 122:
                c -= 32
            if 65 <= c <= 90:
                if first and i + 1 < n and ((65 <= buf[i + 1] <= 90) or (97 <= buf[i + 1] <= 122) or buf[i + 1] == 95):
                    # extended command (Klipper macro, ...): keep, ignore
                    stats[ST_UNKNOWN] += 1
                    while i < n and buf[i] != 10:
                        i += 1
                    break
                first = False
                v, i2, ok = _parse_num(buf, i + 1, n)
                i = i2
                if not ok:  # a bare axis letter (G28 X) names the axis
                    if c == 88:
                        hx = True
                    elif c == 89:
                        hy = True
                    elif c == 90:
                        hz = True
                    continue
                if c == 71:  # G
                    g = int(v + 1e-6)
                    if g <= 3 and abs(v - g) < 1e-6:
                        lmotion = g
                        motion = g
                    elif g == 90:
                        abs_xyz = True
                    elif g == 91:
                        abs_xyz = False
                    elif g == 20:
                        scale = 25.4
                    elif g == 21:
                        scale = 1.0
                    elif g == 28:
                        home = True
                    elif g == 92:
                        setpos = True
                    elif g == 10 or g == 11:
                        stats[ST_FWRETRACT] += 1
                        nonmotion = True
                    elif g == 17 or g == 94:
                        pass
                    else:  # G4, G29, G31, G53 ...: their axis words are not a move
                        nonmotion = True
                        if not (g == 4 or g == 29 or g == 53 or g == 40 or g == 80):
                            stats[ST_UNKNOWN] += 1
                elif c == 77:  # M
                    m = int(v + 1e-6)
                    if m == 82:
                        e_rel = False
                    elif m == 83:
                        e_rel = True
                    elif m == 101:
                        tool_on = True
                        toolon_mode = True
                    elif m == 103:
                        tool_on = False
                    else:
                        # other M codes may carry strings (M117/M118 ...): skip the rest
                        while i < n and buf[i] != 10 and buf[i] != 59:
                            i += 1
                elif c == 84:  # T
                    tool = int(v) if 0 <= v < 255 else tool
                elif c == 88:
                    hx = True
                    vx = v
                elif c == 89:
                    hy = True
                    vy = v
                elif c == 90:
                    hz = True
                    vz = v
                elif c == 69 or c == 65:  # E (A as an alias used by some dialects)
                    he = True
                    ve = v
                elif c == 70:
                    if v > 0:
                        feed = v * scale
                elif c == 73:
                    hi = True
                    vi = v
                elif c == 74:
                    hj = True
                    vj = v
                elif c == 82:
                    hr = True
                    vr = v
                continue
            if c >= 128 or c < 32:
                bad = True
            i += 1
        if bad:
            if stats[ST_BAD] == 0:
                stats[ST_FIRST_BAD] = line
            stats[ST_BAD] += 1
        # ---- execute
        if home:
            all_axes = not (hx or hy or hz)
            if all_axes or hx:
                lx = 0.0
                ox = 0.0
            if all_axes or hy:
                ly = 0.0
                oy = 0.0
            if all_axes or hz:
                lz = 0.0
                oz = 0.0
        elif setpos:
            if not (hx or hy or hz or he):
                ox += lx
                oy += ly
                oz += lz
                lx = ly = lz = e = 0.0
            if hx:
                ox += lx - vx * scale
                lx = vx * scale
            if hy:
                oy += ly - vy * scale
                ly = vy * scale
            if hz:
                oz += lz - vz * scale
                lz = vz * scale
            if he:
                e = ve * scale
        elif (lmotion >= 0 or not nonmotion) and (hx or hy or hz or he) or ((lmotion == 2 or lmotion == 3) and (hi or hj or hr)):
            mo = lmotion if lmotion >= 0 else motion
            x0 = lx + ox
            y0 = ly + oy
            z0 = lz + oz
            if hx:
                lx = vx * scale if abs_xyz else lx + vx * scale
            if hy:
                ly = vy * scale if abs_xyz else ly + vy * scale
            if hz:
                lz = vz * scale if abs_xyz else lz + vz * scale
            de = 0.0
            if he:
                if e_rel or not abs_xyz:
                    de = ve * scale
                else:
                    de = ve * scale - e
                e += de
            x1 = lx + ox
            y1 = ly + oy
            z1 = lz + oz
            if abs(x1) > ABSURD_MM or abs(y1) > ABSURD_MM or abs(z1) > ABSURD_MM or abs(de) > ABSURD_MM:
                if stats[ST_ABSURD] == 0:
                    stats[ST_FIRST_ABSURD] = line
                stats[ST_ABSURD] += 1
            extruding = de > 1e-9 or (toolon_mode and tool_on and not he)
            if not extruding:
                de = 0.0
            dxy = math.hypot(x1 - x0, y1 - y0)
            if mo == 2 or mo == 3:
                stats[ST_ARCS] += 1
                ok, cx, cy, r0, r1, a0, sweep, k = arc_geometry(
                    x0, y0, x1, y1, mo == 3, hi or hj, hr, vi * scale, vj * scale, vr * scale, chord_tol
                )
                if not ok:
                    if stats[ST_ARC_BAD] == 0:
                        stats[ST_FIRST_ARC_BAD] = line
                    stats[ST_ARC_BAD] += 1
                    mo = 1
                else:
                    if extruding:
                        while ns + k >= seg_z.shape[0]:
                            seg_a = _grow_f(seg_a, k)
                            seg_b = _grow_f(seg_b, k)
                            seg_z = _grow_1(seg_z, k)
                            seg_e = _grow_1(seg_e, k)
                            seg_line = _grow_1(seg_line, k)
                            seg_tool = _grow_1(seg_tool, k)
                        px = x0
                        py = y0
                        for q in range(1, k + 1):
                            t = q / k
                            rr = r0 + (r1 - r0) * t
                            if q == k:
                                qx = x1
                                qy = y1
                            else:
                                qx = cx + rr * math.cos(a0 + sweep * t)
                                qy = cy + rr * math.sin(a0 + sweep * t)
                            seg_a[ns, 0] = px
                            seg_a[ns, 1] = py
                            seg_b[ns, 0] = qx
                            seg_b[ns, 1] = qy
                            seg_z[ns] = z0 + (z1 - z0) * t
                            seg_e[ns] = de / k
                            seg_line[ns] = line
                            seg_tool[ns] = tool
                            ns += 1
                            px = qx
                            py = qy
                    elif dxy > 0 or abs(sweep) > 0:
                        if nt >= travel_line.shape[0]:
                            travel_line = _grow_1(travel_line, 16)
                        travel_line[nt] = line
                        nt += 1
            if mo < 2:
                if extruding and dxy > 1e-12:
                    if ns >= seg_z.shape[0]:
                        seg_a = _grow_f(seg_a, 16)
                        seg_b = _grow_f(seg_b, 16)
                        seg_z = _grow_1(seg_z, 16)
                        seg_e = _grow_1(seg_e, 16)
                        seg_line = _grow_1(seg_line, 16)
                        seg_tool = _grow_1(seg_tool, 16)
                    seg_a[ns, 0] = x0
                    seg_a[ns, 1] = y0
                    seg_b[ns, 0] = x1
                    seg_b[ns, 1] = y1
                    seg_z[ns] = z1
                    seg_e[ns] = de
                    seg_line[ns] = line
                    seg_tool[ns] = tool
                    ns += 1
                elif dxy > 1e-12:
                    if nt >= travel_line.shape[0]:
                        travel_line = _grow_1(travel_line, 16)
                    travel_line[nt] = line
                    nt += 1
        if i < n:  # at '\n'
            i += 1
            line += 1
        else:  # last line had no newline
            stats[ST_NONL] = 1
            line += 1
    if toolon_mode:
        stats[ST_TOOLON] = 1
    stats[ST_LINES] = line - 1
    stats[ST_SEG] = ns
    stats[ST_TRAVEL] = nt
    stats[ST_CMT] = nc
    if ns < 0.9 * seg_z.shape[0]:  # give back the slack (a copy only when it is large)
        seg_a = seg_a[:ns].copy()
        seg_b = seg_b[:ns].copy()
        seg_z = seg_z[:ns].copy()
        seg_e = seg_e[:ns].copy()
        seg_line = seg_line[:ns].copy()
        seg_tool = seg_tool[:ns].copy()
    return (
        seg_a[:ns], seg_b[:ns], seg_z[:ns], seg_e[:ns], seg_line[:ns], seg_tool[:ns],
        travel_line[:nt], cmt[:nc], probe_state, stats,
    )
