"""Helpers for the gcode tests: the shared file list and a tiny reference machine."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

_spec = importlib.util.spec_from_file_location(
    "lw_root_conftest", Path(__file__).resolve().parents[1] / "conftest.py"
)
_root = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_root)


def shared_gcode_files() -> list[Path]:
    """Every file in ../shared/data/gcode, whatever its extension (.gcode, .bgcode, FlashPrint's .g ...)."""
    d = _root.SHARED_DATA / "gcode"
    return sorted(p for p in d.glob("*") if p.is_file() and p.suffix.lower() not in {".md", ".txt"}) if d.is_dir() else []


def reference_extrusion(text: str) -> tuple[float, int]:
    """Total filament on XY-moving G0/G1 lines and their count, via the `gcodeparser` package.

    Handles G90/G91, M82/M83 and G92 only (no arcs, no inches): an independent
    implementation to compare the numba machine with.
    """
    from gcodeparser import parse_gcode_lines

    abs_xyz, e_rel = True, False
    pos = {"X": 0.0, "Y": 0.0}
    e = 0.0
    total, count = 0.0, 0
    for ln in parse_gcode_lines(text):
        cmd, p = ln.command, ln.params
        if cmd == ("G", 90):
            abs_xyz = True
        elif cmd == ("G", 91):
            abs_xyz = False
        elif cmd == ("M", 82):
            e_rel = False
        elif cmd == ("M", 83):
            e_rel = True
        elif cmd == ("G", 92) and "E" in p:
            e = float(p["E"])
        elif cmd in (("G", 0), ("G", 1)):
            new = dict(pos)
            for a in "XY":
                if a in p:
                    new[a] = float(p[a]) if abs_xyz else pos[a] + float(p[a])
            de = 0.0
            if "E" in p:
                de = float(p["E"]) if (e_rel or not abs_xyz) else float(p["E"]) - e
                e += de
            if de > 1e-9 and math.hypot(new["X"] - pos["X"], new["Y"] - pos["Y"]) > 1e-12:
                total += de
                count += 1
            pos = new
    return total, count
