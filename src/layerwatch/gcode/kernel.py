"""Numba state machine: G-code bytes -> extruding segments, in one pass.

The kernel lexes the ``uint8`` buffer (no ``str`` copy; :mod:`.lexer`) and runs the modal
machine as it goes (G90/G91, M82/M83, G92, G20/G21, G0-G3, G10/G11, G28,
T, F, M101/M103, M200 D volumetric E, M221 flow). It emits flat arrays of
extruding segments, the lines of travel moves, the byte offsets of ``;``
comments that may be slicer tags (decoded in Python by
:mod:`layerwatch.gcode.tags`), filament totals and, for the post-processor,
the modal state at requested "probe" lines.

Conventions: ``phys = logical + offset`` per axis (G92 changes the offset),
positions in mm (G20 scales by 25.4), E relative when ``M83`` or ``G91``
(Klipper/Marlin semantics: G91 makes E relative too; G90 keeps M83). E words
are filament length unless volumetric (``M200 D<d>`` with d > 0, or the
caller's ``e_area_init`` for UltiGCode), then mm³, divided by the filament
cross-section. ``M221 S<p> [T<t>]`` scales what the printer feeds (``seg_e``
and the "fed" totals) but not the "commanded" totals, which are what slicers
state as "filament used".

The machine state lives in one float64 array (indices ``MS_*``), the words of
the current line in two arrays indexed by letter; each step is a small
function (the hot ones inlined by numba). The lexer (:mod:`.lexer`) and the
arc geometry (:mod:`.arcs`) are compiled into this module's code, so the
on-disk cache is keyed on all three files (:mod:`layerwatch.gcode.jit_cache`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numba as nb
import numpy as np

from layerwatch.gcode import jit_cache
from layerwatch.gcode.arcs import arc_geometry
from layerwatch.gcode.kernel_abi import (
    ABSURD_MM,
    ARC_BUDGET_BASE,
    ARC_BUDGET_PER_BYTE,
    ARC_MAX_CHORDS,
    ARC_MIN_CHORD_MM,
    FS_CMD_HIGH,
    FS_EONLY_FED,
    FS_FED_HIGH,
    FS_XY_CMD,
    FS_XY_FED,
    MS_ABS,
    MS_ARC_BUDGET,
    MS_ARC_CHORDS,
    MS_CMD,
    MS_CMD_HIGH,
    MS_E,
    MS_EAREA,
    MS_EREL,
    MS_FED,
    MS_FED_HIGH,
    MS_FEED,
    MS_FLOW,
    MS_LX,
    MS_LY,
    MS_LZ,
    MS_MOTION,
    MS_OX,
    MS_OY,
    MS_OZ,
    MS_SCALE,
    MS_TOOL,
    MS_TOOLON,
    MS_TOOLON_MODE,
    N_FSTATS,
    N_MS,
    N_PROBE,
    N_STATS,
    N_TOOLS,
    ST_ABSURD,
    ST_ARC_BAD,
    ST_ARC_CAPPED,
    ST_ARCS,
    ST_BAD,
    ST_CMT,
    ST_FIRST_ABSURD,
    ST_FIRST_ARC_BAD,
    ST_FIRST_ARC_CAPPED,
    ST_FIRST_BAD,
    ST_FIRST_MALFORMED,
    ST_FLOW_SET,
    ST_FWRETRACT,
    ST_LINES,
    ST_MALFORMED,
    ST_NONL,
    ST_SEG,
    ST_TOOLON,
    ST_TRAVEL,
    ST_UNKNOWN,
    ST_VOLUMETRIC,
)
from layerwatch.gcode.lexer import (
    BAD_BYTES,
    BAD_WORD,
    MAX_G,
    N_WORDS,
    W_A,
    W_D,
    W_E,
    W_F,
    W_I,
    W_J,
    W_R,
    W_S,
    W_T,
    W_X,
    W_Y,
    W_Z,
    count_g_lines,
    lex_line,
)

# before any njit function below is loaded from disk: drop cached code built from other sources
jit_cache.ensure_fresh(Path(__file__).resolve().parent / "__pycache__", "kernel",
                       jit_cache.cache_key(jit_cache.KERNEL_SOURCES))

# ---- what a line does
ACT_NONE, ACT_HOME, ACT_SETPOS, ACT_MOVE = 0, 1, 2, 3



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
def _apply_g(ms, g, stats):
    """Modal effect of one G word; returns (action, motion or -1, non-motion flag)."""
    gi = int(g + 1e-6) if 0 <= g < 1e6 else 9999
    if gi <= 3 and abs(g - gi) < 1e-6:
        ms[MS_MOTION] = gi
        return ACT_MOVE, gi, False
    if gi == 90:
        ms[MS_ABS] = 1.0
    elif gi == 91:
        ms[MS_ABS] = 0.0
    elif gi == 20:
        ms[MS_SCALE] = 25.4
    elif gi == 21:
        ms[MS_SCALE] = 1.0
    elif gi == 28:
        return ACT_HOME, -1, False
    elif gi == 92:
        return ACT_SETPOS, -1, False
    elif gi == 10 or gi == 11:
        stats[ST_FWRETRACT] += 1
        return ACT_NONE, -1, True
    elif not (gi == 17 or gi == 94):  # G4, G29, G31, G53 ...: their axis words are not a move
        if not (gi == 4 or gi == 29 or gi == 53 or gi == 40 or gi == 80):
            stats[ST_UNKNOWN] += 1
        return ACT_NONE, -1, True
    return ACT_NONE, -1, False


@nb.njit(cache=True)
def _apply_m(ms, m, val, has, stats):
    """Modal effect of an M code (E mode, tool-on dialect, volumetric E, flow)."""
    if m == 82:
        ms[MS_EREL] = 0.0
    elif m == 83:
        ms[MS_EREL] = 1.0
    elif m == 101:
        ms[MS_TOOLON] = 1.0
        ms[MS_TOOLON_MODE] = 1.0
    elif m == 103:
        ms[MS_TOOLON] = 0.0
    elif m == 200 and has[W_D] and math.isfinite(val[W_D]):
        d = val[W_D]
        ms[MS_EAREA] = math.pi * d * d / 4.0 if 0.5 <= d <= 5.0 else 0.0
        if ms[MS_EAREA] > 0:
            stats[ST_VOLUMETRIC] = 1
    elif m == 221 and has[W_S] and math.isfinite(val[W_S]) and 0.0 <= val[W_S] <= 1000.0:
        t = int(val[W_T]) if has[W_T] and 0 <= val[W_T] < N_TOOLS else int(ms[MS_TOOL])
        if t < N_TOOLS:  # tools 16..254 print at 100 %
            ms[MS_FLOW + t] = val[W_S] / 100.0
        stats[ST_FLOW_SET] += 1


@nb.njit(cache=True, inline="always")
def _line_action(ms, val, has, gcodes, ng, mcode, stats):
    """Apply the line's modal words; returns (action, motion of the move)."""
    act = ACT_NONE
    lmotion = -1
    nonmotion = False
    for k in range(ng):
        a, mo, nm = _apply_g(ms, gcodes[k], stats)
        if a != ACT_NONE and (act == ACT_NONE or act == ACT_MOVE):
            act = a
        if mo >= 0:
            lmotion = mo
        nonmotion = nonmotion or nm
    if mcode >= 0:
        _apply_m(ms, mcode, val, has, stats)
    if has[W_T] and mcode != 221:
        t = val[W_T]
        if 0 <= t < 255:
            ms[MS_TOOL] = int(t)
    if has[W_F] and val[W_F] > 0:
        ms[MS_FEED] = val[W_F] * ms[MS_SCALE]
    if act == ACT_HOME or act == ACT_SETPOS:
        return act, -1
    axes = has[W_X] or has[W_Y] or has[W_Z] or has[W_E] or has[W_A]
    arc_words = has[W_I] or has[W_J] or has[W_R]
    if (lmotion >= 0 or not nonmotion) and axes:
        return ACT_MOVE, lmotion if lmotion >= 0 else int(ms[MS_MOTION])
    if (lmotion == 2 or lmotion == 3) and arc_words:
        return ACT_MOVE, lmotion
    return ACT_NONE, -1


@nb.njit(cache=True)
def _home(ms, has):
    """G28: the named axes (all when none) to 0 with their offsets cleared."""
    all_axes = not (has[W_X] or has[W_Y] or has[W_Z])
    for w, lo, oo in ((W_X, MS_LX, MS_OX), (W_Y, MS_LY, MS_OY), (W_Z, MS_LZ, MS_OZ)):
        if all_axes or has[w]:
            ms[lo] = 0.0
            ms[oo] = 0.0


@nb.njit(cache=True)
def _set_position(ms, val, has):
    """G92: logical positions set, physical ones kept (offsets absorb the change)."""
    sc = ms[MS_SCALE]
    if not (has[W_X] or has[W_Y] or has[W_Z] or has[W_E]):
        for lo, oo in ((MS_LX, MS_OX), (MS_LY, MS_OY), (MS_LZ, MS_OZ)):
            ms[oo] += ms[lo]
            ms[lo] = 0.0
        ms[MS_E] = 0.0
    for w, lo, oo in ((W_X, MS_LX, MS_OX), (W_Y, MS_LY, MS_OY), (W_Z, MS_LZ, MS_OZ)):
        if has[w] and math.isfinite(val[w]):
            ms[oo] += ms[lo] - val[w] * sc
            ms[lo] = val[w] * sc
    if has[W_E] and math.isfinite(val[W_E]):
        ms[MS_E] = val[W_E] * sc


@nb.njit(cache=True, inline="always")
def _advance_axes(ms, val, has):
    """Move the logical X/Y/Z and E; returns the filament length commanded (mm, volumetric converted)."""
    sc = ms[MS_SCALE]
    absolute = ms[MS_ABS] > 0
    for w, lo in ((W_X, MS_LX), (W_Y, MS_LY), (W_Z, MS_LZ)):
        if has[w] and math.isfinite(val[w]):
            ms[lo] = val[w] * sc if absolute else ms[lo] + val[w] * sc
    w_e = W_E if has[W_E] else W_A  # A: an alias of E in some dialects
    if not has[w_e] or not math.isfinite(val[w_e]):
        return 0.0
    de = val[w_e] * sc if (ms[MS_EREL] > 0 or not absolute) else val[w_e] * sc - ms[MS_E]
    ms[MS_E] += de
    return de / ms[MS_EAREA] if ms[MS_EAREA] > 0 else de


@nb.njit(cache=True, inline="always")
def _account_filament(ms, fs, de, flow, xy_move):
    """Commanded and fed filament: high-water marks of the cumulative E (retract/deretract pairs count once)."""
    ms[MS_CMD] += de
    ms[MS_FED] += de * flow
    if ms[MS_CMD] > ms[MS_CMD_HIGH]:
        ms[MS_CMD_HIGH] = ms[MS_CMD]
    if ms[MS_FED] > ms[MS_FED_HIGH]:
        if not xy_move:
            fs[FS_EONLY_FED] += ms[MS_FED] - ms[MS_FED_HIGH]
        ms[MS_FED_HIGH] = ms[MS_FED]


@nb.njit(cache=True)
def _arc_chords(ms, k, sweep, r0, r1):
    """Chord count bounded by the arc's length (``ARC_MIN_CHORD_MM``), ``ARC_MAX_CHORDS`` and the file budget."""
    length = abs(sweep) * max(r0, r1)
    cap = min(ARC_MAX_CHORDS, 1 + int(min(length, 1e9) / ARC_MIN_CHORD_MM))
    if ms[MS_ARC_CHORDS] > ms[MS_ARC_BUDGET]:
        cap = min(cap, 16)
    k2 = max(1, min(k, cap))
    ms[MS_ARC_CHORDS] += k2
    return k2, k2 < k


@nb.njit(cache=True, inline="always")
def _push_seg(segf, segi, ns, x0, y0, x1, y1, z, e, line, tool):
    """Append one segment, growing the buffers when full; returns the buffers."""
    if ns >= segf.shape[0]:
        segf = _grow_f(segf, 16)
        segi = _grow_f(segi, 16)
    segf[ns, 0] = x0
    segf[ns, 1] = y0
    segf[ns, 2] = x1
    segf[ns, 3] = y1
    segf[ns, 4] = z
    segf[ns, 5] = e
    segi[ns, 0] = line
    segi[ns, 1] = tool
    return segf, segi


@nb.njit(cache=True)
def _emit_arc(segf, segi, ns, p, arc, k, de, line, tool):
    """Linearise an extruding arc into ``k`` chords. ``p`` = (x0, y0, z0, x1, y1, z1),
    ``arc`` = (cx, cy, r0, r1, a0, sweep); Z and E are shared evenly (helical arcs)."""
    x0, y0, z0, x1, y1, z1 = p
    cx, cy, r0, r1, a0, sweep = arc
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
        segf, segi = _push_seg(segf, segi, ns, px, py, qx, qy, z0 + (z1 - z0) * t, de / k, line, tool)
        ns += 1
        px = qx
        py = qy
    return segf, segi, ns


@nb.njit(cache=True)
def _flag(stats, count_slot, first_slot, line):
    if stats[count_slot] == 0:
        stats[first_slot] = line
    stats[count_slot] += 1


@nb.njit(cache=True, inline="always")
def _move(ms, fs, val, has, mo, chord_tol, segf, segi, ns, line, stats):
    """Execute a G0-G3 move; returns (segf, segi, ns, travelled) where ``travelled`` says a
    non-extruding XY move happened (its line goes to the travel list)."""
    x0 = ms[MS_LX] + ms[MS_OX]
    y0 = ms[MS_LY] + ms[MS_OY]
    z0 = ms[MS_LZ] + ms[MS_OZ]
    de = _advance_axes(ms, val, has)
    x1 = ms[MS_LX] + ms[MS_OX]
    y1 = ms[MS_LY] + ms[MS_OY]
    z1 = ms[MS_LZ] + ms[MS_OZ]
    tool = int(ms[MS_TOOL])
    flow = ms[MS_FLOW + tool] if tool < N_TOOLS else 1.0
    dxy = math.hypot(x1 - x0, y1 - y0)
    absurd = not (abs(x1) <= ABSURD_MM and abs(y1) <= ABSURD_MM and abs(z1) <= ABSURD_MM and abs(de) <= ABSURD_MM
                  and abs(x0) <= ABSURD_MM and abs(y0) <= ABSURD_MM and abs(z0) <= ABSURD_MM)
    if absurd:  # not drawn: the geometry stays finite and on Earth
        _flag(stats, ST_ABSURD, ST_FIRST_ABSURD, line)
        return segf, segi, ns, False
    arc = mo == 2 or mo == 3
    _account_filament(ms, fs, de, flow, dxy > 1e-12 or arc)
    extruding = de > 1e-9 or (ms[MS_TOOLON_MODE] > 0 and ms[MS_TOOLON] > 0 and not has[W_E])
    fed = de * flow if de > 1e-9 else 0.0
    if arc:
        stats[ST_ARCS] += 1
        sc = ms[MS_SCALE]
        ok, cx, cy, r0, r1, a0, sweep, k = arc_geometry(
            x0, y0, x1, y1, mo == 3, has[W_I] or has[W_J], has[W_R],
            val[W_I] * sc if has[W_I] else 0.0, val[W_J] * sc if has[W_J] else 0.0,
            val[W_R] * sc if has[W_R] else 0.0, chord_tol,
        )
        if ok and not (r0 <= ABSURD_MM and r1 <= ABSURD_MM):
            ok = False
        if not ok:
            _flag(stats, ST_ARC_BAD, ST_FIRST_ARC_BAD, line)
        else:
            if not extruding:
                return segf, segi, ns, dxy > 0 or abs(sweep) > 0
            k, capped = _arc_chords(ms, k, sweep, r0, r1)
            if capped:
                _flag(stats, ST_ARC_CAPPED, ST_FIRST_ARC_CAPPED, line)
            fs[FS_XY_CMD] += de
            fs[FS_XY_FED] += fed
            segf, segi, ns = _emit_arc(segf, segi, ns, (x0, y0, z0, x1, y1, z1), (cx, cy, r0, r1, a0, sweep),
                                       k, fed, line, tool)
            return segf, segi, ns, False
    if dxy <= 1e-12:
        return segf, segi, ns, False
    if not extruding:
        return segf, segi, ns, True
    fs[FS_XY_CMD] += max(de, 0.0)
    fs[FS_XY_FED] += fed
    segf, segi = _push_seg(segf, segi, ns, x0, y0, x1, y1, z1, fed, line, tool)
    return segf, segi, ns + 1, False


@nb.njit(cache=True)
def _record_probe(probe_state, row, ms):
    """Modal state at the start of a probed line (columns: see ``N_PROBE``)."""
    for col, slot in enumerate((MS_LX, MS_LY, MS_LZ, MS_OX, MS_OY, MS_OZ, MS_E, MS_FEED, MS_ABS, MS_EREL, MS_TOOL)):
        probe_state[row, col] = ms[slot]
    probe_state[row, 11] = 1.0 if ms[MS_SCALE] != 1.0 else 0.0
    probe_state[row, 12] = 1.0 if (ms[MS_TOOLON_MODE] > 0 and ms[MS_TOOLON] > 0) else 0.0


@nb.njit(cache=True)
def _new_state(e_rel_init, e_area_init, n_bytes):
    ms = np.zeros(N_MS, np.float64)
    ms[MS_ARC_BUDGET] = ARC_BUDGET_BASE + ARC_BUDGET_PER_BYTE * n_bytes
    ms[MS_ABS] = 1.0
    ms[MS_EREL] = 1.0 if e_rel_init else 0.0
    ms[MS_SCALE] = 1.0
    ms[MS_MOTION] = 1.0
    ms[MS_EAREA] = e_area_init
    ms[MS_FLOW : MS_FLOW + N_TOOLS] = 1.0
    return ms


@nb.njit(cache=True)
def _new_outputs(cap):
    """Empty ``(segf, segi, travel_line, cmt)`` for a file of ``cap`` G lines (they grow as needed)."""
    segf = np.empty((cap, 6), np.float64)
    segi = np.empty((cap, 2), np.int64)
    travel_line = np.empty(cap // 4 + 16, np.int64)
    cmt = np.empty((64, 2), np.int64)
    return segf, segi, travel_line, cmt


@nb.njit(cache=True, inline="always")
def _count_lex_problems(stats, line, bad, extended):
    """Count a line the lexer found extended (unknown words), with bad bytes or a malformed word."""
    if extended:
        stats[ST_UNKNOWN] += 1
    if bad & BAD_BYTES:
        _flag(stats, ST_BAD, ST_FIRST_BAD, line)
    if bad & BAD_WORD:
        _flag(stats, ST_MALFORMED, ST_FIRST_MALFORMED, line)


@nb.njit(cache=True)
def run_kernel(buf, probes, chord_tol, e_rel_init=False, e_area_init=0.0):
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
    e_area_init : float
        Filament cross-section, mm², when E is volume from the start (UltiGCode); 0 for lengths.

    Returns
    -------
    segf : (S, 6) float64  x0, y0, x1, y1 (physical mm), z (mm), e (filament fed, mm)
    segi : (S, 2) int64  source line, tool
    travel_line : (T,) int64
    cmt : (C, 2) int64  byte offset of the ';' and its line
    probe_state : (P, N_PROBE) float64
    stats : (N_STATS,) int64
    fstats : (N_FSTATS,) float64  filament totals, mm
    """
    n = buf.shape[0]
    segf, segi, travel_line, cmt = _new_outputs(count_g_lines(buf))
    probe_state = np.full((probes.shape[0], N_PROBE), np.nan)
    stats = np.zeros(N_STATS, np.int64)
    fs = np.zeros(N_FSTATS, np.float64)
    ms = _new_state(e_rel_init, e_area_init, n)
    val = np.zeros(N_WORDS, np.float64)
    has = np.zeros(N_WORDS, np.bool_)
    gcodes = np.zeros(MAX_G, np.float64)
    ns = nt = nc = npb = 0
    line = 1
    i = 0
    while i <= n:
        while npb < probes.shape[0] and probes[npb] <= line:
            if probes[npb] == line:
                _record_probe(probe_state, npb, ms)
            npb += 1
        if i == n:
            break
        i, ng, mcode, cmt_at, bad, extended = lex_line(buf, i, n, val, has, gcodes)
        if cmt_at >= 0:
            if nc >= cmt.shape[0]:
                cmt = _grow_f(cmt, 64)
            cmt[nc, 0] = cmt_at
            cmt[nc, 1] = line
            nc += 1
        _count_lex_problems(stats, line, bad, extended)
        act, mo = _line_action(ms, val, has, gcodes, ng, mcode, stats)
        if act == ACT_HOME:
            _home(ms, has)
        elif act == ACT_SETPOS:
            _set_position(ms, val, has)
        elif act == ACT_MOVE:
            segf, segi, ns, travelled = _move(ms, fs, val, has, mo, chord_tol, segf, segi, ns, line, stats)
            if travelled:
                if nt >= travel_line.shape[0]:
                    travel_line = _grow_1(travel_line, 16)
                travel_line[nt] = line
                nt += 1
        if i < n:  # at '\n'
            i += 1
        else:  # last line had no newline
            stats[ST_NONL] = 1
        line += 1
    _finish_stats(stats, fs, ms, line, ns, nt, nc)
    if ns < 0.9 * segf.shape[0]:  # give back the slack (a copy only when it is large)
        segf = segf[:ns].copy()
        segi = segi[:ns].copy()
    return segf[:ns], segi[:ns], travel_line[:nt], cmt[:nc], probe_state, stats, fs


@nb.njit(cache=True)
def _finish_stats(stats, fs, ms, line, ns, nt, nc):
    if ms[MS_TOOLON_MODE] > 0:
        stats[ST_TOOLON] = 1
    stats[ST_LINES] = line - 1
    stats[ST_SEG] = ns
    stats[ST_TRAVEL] = nt
    stats[ST_CMT] = nc
    fs[FS_CMD_HIGH] = ms[MS_CMD_HIGH]
    fs[FS_FED_HIGH] = ms[MS_FED_HIGH]
