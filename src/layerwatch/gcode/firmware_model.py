"""A per-firmware machine model of G-code modal state, and the checker of prepared files.

:class:`Machine` executes G-code line by line the way a given firmware
interprets it, tracking exactly what the snapshot block must restore: the
XYZ and E positioning modes, the logical and the physical extruder position,
G92 offsets, units, tool, feed rate, firmware retraction, and whether the
moves queued so far have finished (``M400``).

The firmwares differ in one rule that matters here, the coupling of the
extruder mode to ``G90``/``G91``:

Marlin 2.x (:data:`MARLIN`)
    ``G90`` "sets absolute mode; this includes the extruder position unless
    overridden by M83" and ``G91`` likewise makes E relative (marlinfw.org,
    G090/G091 pages). In the 2.x source ``GcodeSuite::set_relative_mode()``
    rewrites the whole ``axis_relative`` bit set, clearing the ``E_MODE_REL``
    bit that ``M83`` set: after ``M83 ... G90`` the next ``G1 E1`` is an
    *absolute* E target. ``M82``/``M83`` then override E only.
Klipper (:data:`KLIPPER`)
    ``klippy/extras/gcode_move.py`` keeps two flags: ``G90``/``G91`` set
    ``absolute_coord``, ``M82``/``M83`` set ``absolute_extrude``; ``G1 E`` is
    relative when *either* says relative (``if not self.absolute_coord or not
    self.absolute_extrude``). ``G90`` therefore never changes what ``M83`` set.
RepRapFirmware (:data:`REPRAP`)
    "RepRapFirmware uses M83 to set the extruder to relative mode: extrusion is
    NOT set to relative using G91" (docs.duet3d.com, G91): ``G90``/``G91`` affect
    the axes only, ``M82``/``M83`` the extruders only.

Common to all three: a bare ``G10``/``G11`` is firmware retraction (``G10``
with ``P``/``L``/``S``/``R`` words sets tool offsets or temperatures in RRF and
is not), ``G92 E`` sets the logical E position without moving the filament,
``M400`` waits until every queued move is finished, ``G4 P<ms>`` dwells.

:func:`check_prepared` runs an original file and its prepared version through
the model and lists every :class:`Violation` of the printer-safety rules
(``DESIGN.md``): a move emitted by layerwatch off the bed or above its height,
E (logical or filament) or any mode not restored after a block, the photo
trigger reached while the head is not parked and still or without a hold at
the park spot, a dwell with the nozzle on the part, an unasked tool change or
pin write, and any difference in the slicer's own moves.
"""

from __future__ import annotations

import copy
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field

from layerwatch.gcode.bed import Bed

__all__ = [
    "MARLIN", "KLIPPER", "REPRAP", "FIRMWARES", "Machine", "Violation", "check_prepared",
    "firmware_from_gcode", "slicer_trace", "BLOCK_START", "BLOCK_END",
]

MARLIN, KLIPPER, REPRAP = "marlin", "klipper", "reprap"
FIRMWARES = (MARLIN, KLIPPER, REPRAP)

#: comment lines that open and close every block layerwatch inserts
BLOCK_START = "; layerwatch snapshot block:"
BLOCK_END = "; layerwatch snapshot block end"
#: a line that makes a host take the photo (any profile)
_TRIGGER = re.compile(r"^(?:@layerwatch|M118\b.*layerwatch snapshot|LAYERWATCH_SNAPSHOT\b|TIMELAPSE_TAKE_FRAME\b"
                      r"|M240\b|RESPOND\b.*layerwatch snapshot)", re.I)
_HOLD_MACRO = "LAYERWATCH_WAIT"
_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))?")
_PAREN = re.compile(r"\([^)]*\)")
_LINE_NO = re.compile(r"[Nn]\d+\s*")
_CODE = re.compile(r"([GgMmTt])(\d+(?:\.\d+)?)(?![\d_])")
_FLAVOR = re.compile(rb"(?m)^;\s*(?:gcode_flavor\s*=\s*|FLAVOR:)\s*([A-Za-z0-9_]+)")
_FLAVORS = {b"marlin": MARLIN, b"marlin2": MARLIN, b"marlinlegacy": MARLIN, b"klipper": KLIPPER,
            b"reprapfirmware": REPRAP}
TOL = 1e-6


def firmware_from_gcode(data: bytes) -> str | None:
    """The firmware a file was sliced for (``gcode_flavor`` / ``;FLAVOR:``), None when unstated or generic.

    Cura's ``;FLAVOR:RepRap`` means "RepRap (Marlin/Sprinter)" and counts as Marlin; Slic3r's
    ``gcode_flavor = reprap`` ("RepRap/Sprinter") is used for Marlin and RepRapFirmware alike: unknown.
    """
    m = _FLAVOR.findall(data[:4096]) or _FLAVOR.findall(data[-262144:])
    if not m:
        return None
    v = m[-1].lower()
    if v == b"reprap" and b";FLAVOR:" in data[:4096]:
        return MARLIN
    return _FLAVORS.get(v)


@dataclass
class State:
    """Modal state of the model, all lengths in mm (the file's XY frame), feed in mm/min."""

    pos: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # machine position
    offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # machine = logical + offset
    e: float = 0.0  # logical E (what G92 E sets)
    filament: float = 0.0  # physical drive position: every E move adds its delta, G92 does not
    axis_rel: bool = False  # G91 in effect (for Marlin: the axis bits of axis_relative)
    e_flag_rel: bool = False  # the E flag (Marlin E_MODE_REL / Klipper not absolute_extrude / RRF drivesRelative)
    inch: bool = False
    tool: int = 0
    feed: float = 0.0
    fw_retracted: bool = False
    retracted: float = 0.0  # filament pulled back since the last extrusion, mm
    synced: bool = True  # every queued move has finished (M400, G4, G28 since the last move)
    tool_on: bool = False  # M101 (extruder on, old RepRap/Skeinforge dialect): moves extrude until M103


@dataclass
class Command:
    """One parsed line: ``code`` such as ``'G1'``, ``'M83'``, ``'T1'``, a macro name, or ``''``."""

    code: str
    words: dict[str, float]
    text: str


def parse(line: str) -> Command:
    """Parse one G-code line (comments, line numbers and checksums dropped).

    Words may be written without spaces (``G1X10Y5E.2``, as MeatPack-decoded
    ``.bgcode`` and many firmwares' own files are).
    """
    raw = line.strip()
    if raw.startswith("@"):
        return Command("@", {}, raw)
    code_part = raw.split(";", 1)[0]
    if "(" in code_part:
        code_part = _PAREN.sub(" ", code_part)
    code_part = code_part.split("*", 1)[0].strip()
    m = _LINE_NO.match(code_part)
    if m:
        code_part = code_part[m.end():]
    if not code_part:
        return Command("", {}, raw)
    m = _CODE.match(code_part)
    if m:
        num = m.group(2).split(".")[0].lstrip("0") or "0"
        words = {k: float(v) for k, v in _WORD.findall(code_part[m.end():].upper()) if v}
        if "A" in words and "E" not in words:  # Miracle-Grue (MakerBot) extrudes on the A axis
            words["E"] = words.pop("A")
        return Command(m.group(1).upper() + num, words, raw)
    return Command(code_part.split(None, 1)[0].upper(), {}, raw)  # a macro / extended command (Klipper)


class Machine:
    """Executes G-code under one firmware's rules (see the module docstring).

    Parameters
    ----------
    firmware : {"marlin", "klipper", "reprap"}
    """

    def __init__(self, firmware: str) -> None:
        if firmware not in FIRMWARES:
            raise ValueError(f"unknown firmware {firmware!r}")
        self.firmware = firmware
        self.s = State()

    def e_relative(self) -> bool:
        """True when the next ``G1 E`` is relative under this firmware."""
        if self.firmware == KLIPPER:
            return self.s.axis_rel or self.s.e_flag_rel
        return self.s.e_flag_rel

    def snapshot(self) -> State:
        """A copy of the current state."""
        c = copy.copy(self.s)
        c.pos, c.offset = list(self.s.pos), list(self.s.offset)
        return c

    def execute(self, cmd: Command) -> None:
        """Apply one parsed command to the state."""
        s, c, w = self.s, cmd.code, cmd.words
        if c in ("G0", "G1", "G2", "G3"):
            self._move(w)
        elif c == "G90" or c == "G91":
            s.axis_rel = c == "G91"
            if self.firmware == MARLIN:  # set_relative_mode() rewrites the E bits too
                s.e_flag_rel = s.axis_rel
        elif c == "M82" or c == "M83":
            s.e_flag_rel = c == "M83"
        elif c == "G92":
            self._set_position(w)
        elif c == "G20" or c == "G21":
            s.inch = c == "G20"
        elif c == "G10" and not (w.keys() & {"P", "L", "S", "R"}):
            s.fw_retracted, s.synced = True, False
        elif c == "G11":
            s.fw_retracted, s.synced = False, False
        elif c in ("M400", "G4", "G28"):
            s.synced = True
            if c == "G28":
                axes = [i for i, k in enumerate("XYZ") if k in w] or [0, 1, 2]
                for i in axes:
                    s.pos[i], s.offset[i] = 0.0, 0.0
        elif c == "M101" or c == "M103":
            s.tool_on = c == "M101"
        elif c.startswith("T") and c[1:].isdigit():
            s.tool = int(c[1:])
        if "F" in w and c in ("G0", "G1", "G2", "G3"):
            s.feed = w["F"] * (25.4 if s.inch else 1.0)

    def _move(self, w: dict[str, float]) -> None:
        s = self.s
        k = 25.4 if s.inch else 1.0
        for i, a in enumerate("XYZ"):
            if a in w:
                v = w[a] * k
                new = s.pos[i] + v if s.axis_rel else v + s.offset[i]
                if new != s.pos[i]:
                    s.synced = False
                s.pos[i] = new
        if "E" in w:
            v = w["E"] * k
            de = v if self.e_relative() else v - s.e
            s.e += de
            s.filament += de
            if de != 0.0:
                s.synced = False
            if de < 0:
                s.retracted -= de
            elif de > 0:
                s.retracted = max(0.0, s.retracted - de)

    def _set_position(self, w: dict[str, float]) -> None:
        s = self.s
        k = 25.4 if s.inch else 1.0
        if not w:  # bare G92: every axis to 0
            w = {"X": 0.0, "Y": 0.0, "Z": 0.0, "E": 0.0}
        for i, a in enumerate("XYZ"):
            if a in w:
                s.offset[i] = s.pos[i] - w[a] * k
        if "E" in w:
            s.e = w["E"] * k

    def logical(self) -> tuple[float, float, float]:
        """The current logical (G-code) position X, Y, Z, mm."""
        (x, y, z), (ox, oy, oz) = self.s.pos, self.s.offset
        return x - ox, y - oy, z - oz


@dataclass(frozen=True)
class Violation:
    """One broken safety rule: ``kind``, 1-based ``line`` of the prepared file, ``detail``."""

    kind: str
    line: int
    detail: str


def _lines(data: bytes) -> Iterator[str]:
    for raw in data.split(b"\n"):
        yield raw.decode("latin-1").rstrip("\r")


def slicer_trace(data: bytes, firmware: str) -> list[tuple]:
    """(x, y, z, filament) after every slicer move of ``data`` outside layerwatch blocks (machine mm)."""
    m, out, inside = Machine(firmware), [], False
    for text in _lines(data):
        st = text.strip()
        if st.startswith(BLOCK_START):
            inside = True
        elif st.startswith(BLOCK_END):
            inside = False
        cmd = parse(text)
        if not cmd.code:
            continue
        m.execute(cmd)
        if not inside and cmd.code in ("G0", "G1", "G2", "G3") and cmd.words.keys() & set("XYZE"):
            out.append((*m.s.pos, m.s.filament))
    return out


@dataclass
class _Block:
    start: State
    line: int
    park: tuple[float, float] | None = None
    triggered: bool = False
    held: bool = False


def check_prepared(
    prepared: bytes, firmware: str, bed: Bed, *, original: bytes | list | None = None,
    allow_tools: bool = False, allow_pins: bool = False,
) -> list[Violation]:
    """Every violation of the printer-safety rules in ``prepared`` under ``firmware``.

    Parameters
    ----------
    prepared : bytes
        G-code written by :func:`layerwatch.gcode.snapshot.insert_snapshots`.
    firmware : {"marlin", "klipper", "reprap"}
    bed : Bed
        The bed every emitted move must stay on (XY inside the outline, Z up to
        ``bed.max_z_mm`` when known). The slicer's own moves are not checked
        against it: a purge line may lie outside the printable area on purpose.
    original : bytes or list, optional
        The file before preparation (or its :func:`slicer_trace`): its slicer moves
        (machine position and filament drive position after each) must be exactly those of ``prepared``.
    allow_tools, allow_pins : bool
        Whether ``T<n>`` / ``M42`` inside a block were asked for by the user.

    Returns
    -------
    list of Violation
        Empty when the file is safe.
    """
    m, out, blk, trace = Machine(firmware), [], None, []
    for n, text in enumerate(_lines(prepared), start=1):
        st = text.strip()
        if st.startswith(BLOCK_START):
            blk = _Block(m.snapshot(), n)
            continue
        if blk is None:
            cmd = parse(text)
            if cmd.code:
                m.execute(cmd)
                if cmd.code in ("G0", "G1", "G2", "G3") and cmd.words.keys() & set("XYZE"):
                    trace.append((*m.s.pos, m.s.filament))
            continue
        if st.startswith(BLOCK_END):
            out += _restored(blk.start, m, n)
            if not blk.triggered:
                out.append(Violation("no_trigger", n, "block without a photo trigger"))
            elif not blk.held:
                out.append(Violation("no_hold", n, "no dwell at the park spot after the trigger"))
            blk = None
            continue
        cmd = parse(text)
        if _TRIGGER.match(st) and not blk.triggered:
            out += _at_trigger(blk, m, n)
        if cmd.code in ("G0", "G1", "G2", "G3"):
            out += _emitted_move(blk, m, cmd, n, bed)
            continue
        out += _emitted_other(blk, m, cmd, n, allow_tools, allow_pins)
        m.execute(cmd)
    if blk is not None:
        out.append(Violation("unclosed_block", blk.line, "block never closed"))
    if original is not None:
        out += _same_trace(original if isinstance(original, list) else slicer_trace(original, firmware), trace)
    return out


def _at_trigger(blk: _Block, m: Machine, n: int) -> list[Violation]:
    """The photo trigger: every move finished, the head at the block's park spot, not below the layer."""
    blk.triggered, out = True, []
    if not m.s.synced:
        out.append(Violation("not_still", n, "trigger before the moves finished (no M400)"))
    if blk.park is None or any(abs(a - b) > TOL for a, b in zip(m.s.pos[:2], blk.park, strict=True)):
        out.append(Violation("not_parked", n, f"trigger with the head at {m.s.pos[:2]}, not parked"))
    if m.s.pos[2] < blk.start.pos[2] - TOL:
        out.append(Violation("not_parked", n, "trigger with the nozzle below the layer"))
    return out


def _emitted_move(blk: _Block, m: Machine, cmd: Command, n: int, bed: Bed) -> list[Violation]:
    """A move layerwatch emitted: no extrusion, not between trigger and hold, on the bed, not below the layer."""
    out = []
    if m.s.tool_on and cmd.words.keys() & set("XYZ"):
        out.append(Violation("extrudes", n, "move with the extruder switched on (M101)"))
    if blk.triggered and not blk.held and cmd.words.keys() & set("XYZE"):
        out.append(Violation("not_still", n, "the head moves right after the trigger, before any hold"))
    m.execute(cmd)
    x, y, z = m.s.pos
    if not bed.contains(x, y):
        out.append(Violation("off_bed", n, f"move to X{x:g} Y{y:g} outside {bed.describe()}"))
    if bed.max_z_mm is not None and z > bed.max_z_mm + TOL:
        out.append(Violation("off_bed", n, f"Z{z:g} above the bed's height {bed.max_z_mm:g}"))
    if z < blk.start.pos[2] - TOL:
        out.append(Violation("below_layer", n, f"Z{z:g} below the layer's Z {blk.start.pos[2]:g}"))
    if not blk.triggered and "X" in cmd.words and "Y" in cmd.words:
        blk.park = (x, y)
    return out


def _emitted_other(blk: _Block, m: Machine, cmd: Command, n: int, allow_tools: bool,
                   allow_pins: bool) -> list[Violation]:
    """Any other emitted line: dwells only at the park spot, no unasked tool change or pin write."""
    out = []
    if cmd.code == "G4" or cmd.code == _HOLD_MACRO:
        on_part = any(abs(a - b) <= TOL for a, b in zip(m.s.pos[:2], blk.start.pos[:2], strict=True))
        if on_part or blk.park is None:
            out.append(Violation("dwell_on_part", n, "dwell with the nozzle where it printed"))
        if blk.triggered:
            blk.held = True
    if cmd.code.startswith("T") and cmd.code[1:].isdigit() and not allow_tools:
        out.append(Violation("tool_change", n, f"{cmd.code} emitted, not asked for"))
    if cmd.code == "M42" and not allow_pins:
        out.append(Violation("pin_write", n, "M42 emitted, not asked for"))
    return out


def _restored(before: State, m: Machine, line: int) -> list[Violation]:
    """Violations of 'the block leaves every modal value as the slicer had it'."""
    a, out = m.s, []
    if abs(a.e - before.e) > TOL:
        out.append(Violation("e_not_restored", line, f"logical E {a.e:.5f} after the block, {before.e:.5f} before"))
    if abs(a.filament - before.filament) > TOL:
        out.append(Violation("e_not_restored", line,
                             f"filament moved by {a.filament - before.filament:+.4f} mm over the block"))
    pairs = {"position": (a.pos, before.pos), "offset": (a.offset, before.offset)}
    for name, (p, q) in pairs.items():
        if any(not math.isclose(u, v, abs_tol=TOL) for u, v in zip(p, q, strict=True)):
            out.append(Violation("state_not_restored", line, f"{name} {p} after the block, {q} before"))
    for name in ("axis_rel", "e_flag_rel", "inch", "tool", "fw_retracted", "tool_on"):
        if getattr(a, name) != getattr(before, name):
            out.append(Violation("state_not_restored", line, f"{name} {getattr(before, name)} -> {getattr(a, name)}"))
    if before.feed > 0 and abs(a.feed - before.feed) > TOL:
        out.append(Violation("state_not_restored", line, f"feed {a.feed:g} after the block, {before.feed:g} before"))
    return out


def _same_trace(a: list[tuple], b: list[tuple]) -> list[Violation]:
    if len(a) != len(b):
        return [Violation("slicer_moves_changed", 0, f"{len(a)} slicer moves before, {len(b)} after")]
    for k, (p, q) in enumerate(zip(a, b, strict=True)):
        if any(abs(u - v) > TOL for u, v in zip(p, q, strict=True)):
            return [Violation("slicer_moves_changed", 0, f"slicer move {k}: {q} instead of {p}")]
    return []
