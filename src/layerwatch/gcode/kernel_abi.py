"""The G-code kernel's interface: slots of its state and statistics arrays, its limits.

Shared by the numba kernel (:mod:`.kernel`) and the ahead-of-time compiled one
(``_ckernel.c``, which repeats these numbers and exposes them as ``_ckernel.ABI``
for the test that compares both kernels); imported by :mod:`.reader` without
loading numba. Numba compiles these values into the kernel as constants, so this
file is one of the kernel's cache keys (:data:`.jit_cache.KERNEL_SOURCES`).
"""

from __future__ import annotations

# ---- stats slots (int64)
ST_LINES, ST_SEG, ST_TRAVEL, ST_CMT, ST_BAD, ST_FIRST_BAD, ST_UNKNOWN, ST_ABSURD = 0, 1, 2, 3, 4, 5, 6, 7
ST_FIRST_ABSURD, ST_TOOLON, ST_ARCS, ST_ARC_BAD, ST_FIRST_ARC_BAD, ST_NONL, ST_FWRETRACT = 8, 9, 10, 11, 12, 13, 14
ST_VOLUMETRIC, ST_ARC_CAPPED, ST_FIRST_ARC_CAPPED, ST_FLOW_SET, ST_MALFORMED, ST_FIRST_MALFORMED = 15, 16, 17, 18, 19, 20
N_STATS = 22
# ---- filament totals (float64, mm of filament)
FS_XY_CMD, FS_CMD_HIGH, FS_FED_HIGH, FS_EONLY_FED, FS_XY_FED = 0, 1, 2, 3, 4
N_FSTATS = 5
#: probe state columns: logical x, y, z, offsets x, y, z, e, feed (mm/min), abs_xyz, e_rel_flag, tool, inch,
#: tool-on (M101 dialect, 1 when the extruder is switched on)
N_PROBE = 13
ABSURD_MM = 1.0e5
#: at most this many chords per arc, and in the whole file ARC_BUDGET_BASE + ARC_BUDGET_PER_BYTE x its
#: size (then 16 per arc): memory stays proportional to the file whatever its radii
ARC_MAX_CHORDS = 2048
ARC_BUDGET_BASE = 200_000
ARC_BUDGET_PER_BYTE = 8
ARC_MIN_CHORD_MM = 0.02

# ---- machine state slots (float64)
MS_LX, MS_LY, MS_LZ, MS_OX, MS_OY, MS_OZ, MS_E, MS_FEED = 0, 1, 2, 3, 4, 5, 6, 7
MS_ABS, MS_EREL, MS_SCALE, MS_TOOL, MS_TOOLON, MS_TOOLON_MODE, MS_MOTION, MS_EAREA = 8, 9, 10, 11, 12, 13, 14, 15
MS_CMD, MS_CMD_HIGH, MS_FED, MS_FED_HIGH, MS_ARC_CHORDS, MS_ARC_BUDGET = 16, 17, 18, 19, 20, 21
MS_FLOW = 24  # + tool index, 16 tools
N_TOOLS = 16
N_MS = MS_FLOW + N_TOOLS
