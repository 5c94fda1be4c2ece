"""Insert a snapshot block after every (Nth) layer: safe by construction.

The block follows the paper's Table 1 (retract, lift, park out of the
camera's view, trigger, return), built so that it cannot hurt the print on
Marlin, Klipper or RepRapFirmware (their rules: :mod:`layerwatch.gcode.firmware_model`):

1. **Where.** After the last extruding move of the layer and after the
   slicer's own retraction/wipe that follows it (if any), before its Z move,
   travel or next extrusion. The slicer's retraction then counts towards the
   block's: a Bowden printer's 5 mm is not followed by another 1 mm.
2. **Modes.** The block sets ``G90`` *then* ``M83`` (under Marlin ``G90``
   also makes E absolute, so the order matters), moves in absolute XYZ with
   relative E, and at its end restores the state the firmware had: ``G92 E``
   back to the saved logical E when the file's E is absolute, then the file's
   ``G90``/``G91``, then its ``M82``/``M83`` (this order reproduces every
   combination under all three firmwares), ``G20`` if the file was in inches,
   the feed rate. The saved state is tracked with ``--firmware``, else Klipper
   for the ``klipper``/``timelapse`` profiles, else the firmware the file was
   sliced for (``gcode_flavor``), else with all three, which must then agree.
3. **Retraction.** Firmware retraction (``G10``/``G11``) when the file uses
   it and has not retracted yet; otherwise ``G1 E-r`` / ``G1 E+r`` for what is
   missing to the wanted length (the file's ``retract_length`` when stated).
4. **Where to park.** Inside the bed the file was sliced for
   (:mod:`layerwatch.gcode.bed`), ``PARK_MARGIN_MM`` from its edge, as far as
   possible from the print; an explicit park outside the bed is refused.
   The lift never goes above the bed's height when it is known.
5. **Hold.** ``M400`` at the park spot, then the trigger, then the hold: a
   bounded ``G4`` dwell, or for the ``klipper`` profile ``LAYERWATCH_WAIT``
   steps that end as soon as the host confirms the frame (see
   :mod:`layerwatch.gcode.klipper_macros`). Then back to the saved XY, down
   to the saved Z, un-retract. The nozzle never dwells on the part.
6. **Nothing unasked.** No tool change and no ``M42`` pin write unless
   ``light_tool`` / ``indicator_pin`` are configured (paper profile).

Trigger profiles: ``octoprint`` (``@layerwatch ...`` host command + ``M118``),
``klipper`` (``LAYERWATCH_SNAPSHOT``), ``timelapse`` (``RESPOND`` + moonraker-timelapse's
``TIMELAPSE_TAKE_FRAME``), ``m240`` (``M118`` + ``M240``), ``paper`` (``M118``,
optionally light tool and indicator pin as in the paper's set-up).

References
----------
Paper, Table 1 (G-code inserted after each layer).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from layerwatch.errors import ConfigError, GcodeError
from layerwatch.gcode.bed import Bed, bed_from_gcode, choose_park
from layerwatch.gcode.firmware_model import (
    BLOCK_END,
    BLOCK_START,
    FIRMWARES,
    KLIPPER,
    Machine,
    State,
    firmware_from_gcode,
    parse,
)
from layerwatch.gcode.reader import guess_relative_e, read_toolpath
from layerwatch.gcode.settings import PrinterProfile, SnapshotSettings

__all__ = ["PROFILES", "Prepared", "Plan", "prepare_gcode", "plan_snapshots", "render", "insert_snapshots", "trigger_lines", "hold_steps"]

PROFILES = ("paper", "octoprint", "klipper", "timelapse", "m240")
#: M-codes the scan for the slicer's retraction may step over (fan, acceleration, flow, progress, labels)
_HARMLESS = {"M73", "M104", "M106", "M107", "M117", "M140", "M201", "M203", "M204", "M205", "M220", "M221",
             "M486", "M532", "M572", "M900", "G92"}
#: at most this many lines are scanned after a layer's last extrusion
_SCAN_LINES = 80
_RETRACT_LENGTH = re.compile(rb"(?m)^;\s*(?:retract_length|retraction_length)\s*=\s*([0-9.]+)")
#: interval of the Klipper hold steps, s
HOLD_STEP_S = 0.5


def _f(v: float, digits: int = 4) -> str:
    s = f"{v:.{digits}f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def trigger_lines(profile: str, layer: int, z: float, snapshot: SnapshotSettings) -> list[str]:
    """The trigger lines of ``profile`` for ``layer`` at height ``z`` (mm), without hold or light."""
    msg = f"layerwatch snapshot layer={layer} z={z:.3f}"
    if profile == "octoprint":
        return [f"@{msg}", f"M118 E1 {msg}"]
    if profile == "klipper":
        return [f"LAYERWATCH_SNAPSHOT LAYER={layer} Z={z:.3f}"]
    if profile == "timelapse":
        return [f'RESPOND MSG="{msg}"', "TIMELAPSE_TAKE_FRAME"]
    if profile == "m240":
        return [f"M118 E1 {msg}", "M240"]
    if profile == "paper":
        return [f"M118 E1 {msg}"]
    raise ValueError(f"unknown snapshot profile {profile!r}")


def hold_steps(snapshot: SnapshotSettings) -> int:
    """Number of ``LAYERWATCH_WAIT`` steps of :data:`HOLD_STEP_S` in the Klipper hold (time-out ``hold_s``)."""
    return max(1, math.ceil(snapshot.hold_s / HOLD_STEP_S - 1e-9))


@dataclass
class _Site:
    """Where a block goes: before 0-based line ``at``; the state there under each tracked firmware."""

    at: int
    layer: int
    z: float
    states: dict[str, State]


@dataclass
class Prepared:
    """Result of :func:`prepare_gcode`: the new G-code and what was decided."""

    data: bytes
    bed: Bed
    park_xy_mm: tuple[float, float]
    firmware: str
    blocks: int
    notes: list[str] = field(default_factory=list)


def _find_sites(lines: list[bytes], targets: list[tuple], firmwares: tuple[str, ...],
                e_rel_guess: bool) -> list[_Site]:
    """Run the machine model(s) over ``lines``; one :class:`_Site` per ``(last_line0, layer, z, xyz)`` target.

    ``xyz`` is where the G-code reader ends the layer's last extruding segment: the model must
    agree (two independent parsers), else the file is refused rather than a block written from
    a position layerwatch did not follow.
    """
    machines = [Machine(f) for f in firmwares]
    if e_rel_guess:
        for m in machines:
            m.s.e_flag_rel = True
    sites: list[_Site] = []
    want = dict((t[0], t) for t in targets)
    pend: _Site | None = None
    budget = 0
    for i, raw in enumerate(lines):
        cmd = parse(raw.decode("latin-1"))
        pre = machines[0].snapshot() if pend is not None and cmd.code else None
        if cmd.code:
            for m in machines:
                m.execute(cmd)
        if pend is not None:
            budget -= 1
            verdict = "pass" if pre is None else _classify(cmd, pre, machines[0].s)
            if verdict == "retract":
                pend.at, pend.states = i + 1, {m.firmware: m.snapshot() for m in machines}
            if verdict == "stop" or budget <= 0:
                sites.append(pend)
                pend = None
        if i in want:
            if pend is not None:
                sites.append(pend)
            _, layer, z, xyz = want[i]
            _agree(machines[0], xyz, i, raw)
            pend = _Site(i + 1, layer, z, {m.firmware: m.snapshot() for m in machines})
            budget = _SCAN_LINES
    if pend is not None:
        sites.append(pend)
    return sites


def _agree(m: Machine, xyz: tuple[float, float, float], i: int, raw: bytes) -> None:
    """Refuse when the machine model and the reader disagree on where a layer's last extrusion ends."""
    got = m.s.pos
    if any(abs(a - b) > 1e-3 for a, b in zip(got, xyz, strict=True)):
        text = raw.decode("latin-1").strip()[:60]
        raise GcodeError(
            f"line {i + 1} ({text!r}): layerwatch cannot follow this file's position here (reader at "
            f"{tuple(round(v, 3) for v in xyz)}, machine model at {tuple(round(v, 3) for v in got)}); "
            "no snapshot block was written. Please report the file."
        )


def _classify(cmd, pre: State, post: State) -> str:
    """'retract' (the slicer pulls filament back), 'pass' (harmless), or 'stop' (insert before this line)."""
    c = cmd.code
    if c in ("G0", "G1", "G2", "G3"):
        de = post.filament - pre.filament
        if post.pos[2] != pre.pos[2] or de > 0:
            return "stop"
        if de < 0:
            return "retract"
        return "stop" if post.pos[:2] != pre.pos[:2] else "pass"
    if c == "G10" and post.fw_retracted and not pre.fw_retracted:
        return "retract"
    return "pass" if c in _HARMLESS else "stop"


def _block(st: State, firmware: str, site: _Site, snap: SnapshotSettings, park: tuple[float, float],
           z_top: float | None, retract_mm: float, fw_retract: bool) -> list[str]:
    """The lines of one block for the state ``st`` before it (see the module docstring for the order)."""
    (ox, oy, oz), (mx, my, mz) = st.offset, st.pos
    tf, zf, rf = _f(snap.travel_feed_mm_min), _f(snap.z_feed_mm_min), _f(snap.retract_feed_mm_min)
    lz = mz + snap.lift_mm if z_top is None else min(mz + snap.lift_mm, z_top)
    out = [f"{BLOCK_START} layer {site.layer} z={site.z:.3f}"]
    out += ["G21"] if st.inch else []
    out += ["G90", "M83"]
    out += ["M103"] if st.tool_on else []
    extra = 0.0
    if fw_retract:
        out += [] if st.fw_retracted else ["G10"]
    else:
        extra = float(_f(max(0.0, retract_mm - st.retracted)))
        out += [f"G1 E-{_f(extra)} F{rf}"] if extra > 0 else []
    lifted = lz > mz + 1e-9
    out += [f"G1 Z{_f(lz - oz)} F{zf}"] if lifted else []
    out += [f"G1 X{_f(park[0] - ox)} Y{_f(park[1] - oy)} F{tf}", "M400"]
    if snap.light_tool is not None:
        out.append(f"T{snap.light_tool} ; light platform on (configured light_tool)")
    if snap.indicator_pin is not None:
        out.append(f"M42 P{snap.indicator_pin} S255 ; indicator on (configured indicator_pin)")
    out += trigger_lines(snap.profile, site.layer, site.z, snap)
    if snap.indicator_pin is not None:
        out.append(f"M42 P{snap.indicator_pin} S0 ; indicator off")
    if snap.profile == "klipper":
        k = hold_steps(snap)
        out += [f"LAYERWATCH_WAIT LAYER={site.layer} STEP={i} OF={k}" for i in range(k)]
    else:
        out.append(f"G4 P{snap.settle_ms}")
    if snap.light_tool is not None:
        out.append(f"T{st.tool} ; back to the print tool")
    out.append(f"G1 X{_f(mx - ox, 6)} Y{_f(my - oy, 6)} F{tf}")  # back exactly where the slicer left it
    out += [f"G1 Z{_f(mz - oz, 6)} F{zf}"] if lifted else []
    if fw_retract and not st.fw_retracted:
        out.append("G11")
    out += [f"G1 E{_f(extra)} F{rf}"] if extra > 0 else []
    e_rel = st.e_flag_rel or (firmware == KLIPPER and st.axis_rel)
    if not e_rel:
        out.append(f"G92 E{_f(st.e, 6)}")
    out += ["G20"] if st.inch else []
    out += ["G91" if st.axis_rel else "G90", "M83" if st.e_flag_rel else "M82"]
    out += ["M101"] if st.tool_on else []
    if st.feed > 0:
        out.append(f"G1 F{_f(st.feed / 25.4 if st.inch else st.feed, 6)}")
    out.append(BLOCK_END)
    return out


def _pick_firmware(data: bytes, firmware: str | None, snap: SnapshotSettings, printer: PrinterProfile) -> tuple:
    """Whose rules: ``--firmware``; Klipper for the profiles that only run on Klipper; the file's flavor;
    the configured ``[printer] firmware``; else all three (which must then agree)."""
    if firmware is not None:
        if firmware not in FIRMWARES:
            raise ConfigError(f"unknown firmware {firmware!r}; use one of {', '.join(FIRMWARES)}.")
        return (firmware,)
    if snap.profile in ("klipper", "timelapse"):
        return (KLIPPER,)
    stated = firmware_from_gcode(data)
    if stated is not None:
        return (stated,)
    if "firmware" in printer.model_fields_set and printer.firmware in FIRMWARES:
        return (printer.firmware,)
    return FIRMWARES


def _pick_bed(data: bytes, bed: Bed | None, printer: PrinterProfile) -> Bed:
    if bed is not None:
        return bed
    stated = bed_from_gcode(data)
    if stated is not None:
        return stated
    lo, hi = printer.volume_min_mm, printer.volume_max_mm
    if not all(b - a >= 1 for a, b in zip(lo, hi, strict=True)):
        raise ConfigError(f"[printer] volume {lo}..{hi} is empty; set volume_min_mm < volume_max_mm.")
    poly = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]], np.float64)
    return Bed(poly, float(hi[2]), "[printer] volume")


def _check_part_on_bed(tp, bed: Bed) -> None:
    """The print (after its first layer, which may hold an off-bed purge line) must lie on ``bed``."""
    if tp.n_layers < 2:
        return
    k = tp.layers[1].seg_start
    pts = np.concatenate([tp.start[k:], tp.end[k:]])
    if pts.size == 0:
        return
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    x0, y0, x1, y1 = bed.bounds
    tol = 1.0
    if lo[0] < x0 - tol or lo[1] < y0 - tol or hi[0] > x1 + tol or hi[1] > y1 + tol:
        raise ConfigError(
            f"the print spans X {lo[0]:.1f}..{hi[0]:.1f}, Y {lo[1]:.1f}..{hi[1]:.1f} mm, off the bed "
            f"{bed.describe()}: that is not the bed it was sliced for; pass --bed WxH (or a polygon)."
        )


def _retract_length(data: bytes, snap: SnapshotSettings) -> float:
    """The wanted retraction: ``retract_mm`` if set explicitly, else the file's first ``retract_length``."""
    if "retract_mm" in snap.model_fields_set:
        return snap.retract_mm
    m = _RETRACT_LENGTH.search(data)
    if m:
        v = float(m.group(1))
        if 0 <= v <= 20:
            return v
    return snap.retract_mm


def prepare_gcode(data: bytes, snapshot: SnapshotSettings, printer: PrinterProfile | None = None, *,
                  bed: Bed | None = None, firmware: str | None = None) -> Prepared:
    """Insert a snapshot block after every ``snapshot.every_n_layers``-th layer (and the last).

    :func:`plan_snapshots` then :func:`render`; see :func:`plan_snapshots` for the parameters.
    """
    plan = plan_snapshots(data, snapshot, printer, bed=bed, firmware=firmware)
    if isinstance(plan, Prepared):
        return plan
    return render(plan, snapshot)


def plan_snapshots(data: bytes, snapshot: SnapshotSettings, printer: PrinterProfile | None = None, *,
                   bed: Bed | None = None, firmware: str | None = None) -> Plan | Prepared:
    """Where the snapshot blocks go: the bed, the park spot, the firmware, the state at each block.

    Parameters
    ----------
    data : bytes
        ASCII G-code (decode ``.bgcode`` with :func:`layerwatch.gcode.reader.load_bytes`).
    snapshot : SnapshotSettings
    printer : PrinterProfile, optional
        Its volume is the bed when neither ``bed`` nor the file states one;
        its ``firmware``, when set explicitly, is used if the file states none.
    bed : Bed, optional
        The bed to park on (``--bed``); default: the one the file states.
    firmware : {"marlin", "klipper", "reprap"}, optional
        Whose rules the saved state follows; default: Klipper for the ``klipper`` and
        ``timelapse`` profiles, else the file's ``gcode_flavor``, else all three.

    Returns
    -------
    Plan
        Or, for a file without printed layers, the unchanged file as :class:`Prepared`.

    Raises
    ------
    ConfigError
        Park spot outside the bed, print off the bed, or a firmware-dependent E mode with no firmware known.
    """
    printer = printer or PrinterProfile()
    the_bed = _pick_bed(data, bed, printer)
    fws = _pick_firmware(data, firmware, snapshot, printer)
    tp = read_toolpath(data)
    if tp.n_layers == 0:
        return Prepared(bytes(data), the_bed, (math.nan, math.nan), fws[0], 0, ["no printed layers: nothing inserted"])
    _check_part_on_bed(tp, the_bed)
    if snapshot.park_xy_mm is not None:
        park = (float(snapshot.park_xy_mm[0]), float(snapshot.park_xy_mm[1]))
        if not the_bed.contains(*park):
            raise ConfigError(f"park spot X{park[0]:g} Y{park[1]:g} is outside the bed {the_bed.describe()}; "
                              "choose --park inside it (or leave it out to use a corner).")
    else:
        park = choose_park(the_bed, tp.bounds)
    n = snapshot.every_n_layers
    chosen = [lay for lay in tp.layers if (lay.index + 1) % n == 0 or lay.index == tp.n_layers - 1]
    notes = [f"bed {the_bed.describe()}, park X{park[0]:g} Y{park[1]:g}"]
    lines = data.split(b"\n")
    targets = [(int(tp.line[lay.seg_stop - 1]) - 1, lay.index, float(lay.z),
                (float(tp.end[lay.seg_stop - 1, 0]), float(tp.end[lay.seg_stop - 1, 1]), float(tp.z[lay.seg_stop - 1])))
               for lay in chosen]
    sites = _find_sites(lines, targets, fws, guess_relative_e(data))
    fw = fws[0] if len(fws) == 1 else _agreed_firmware(sites)
    notes.append(f"firmware rules: {fw}" + (" (all three agree)" if len(fws) > 1 else ""))
    fw_retract = any(parse(ln.decode("latin-1")).code == "G10" and not parse(ln.decode("latin-1")).words
                     for ln in lines if ln.lstrip()[:3].upper() == b"G10")
    return Plan(bytes(data), lines, sites, fw, the_bed, park, _retract_length(data, snapshot), fw_retract, notes)


@dataclass
class Plan:
    """Where the blocks go and the state at each: everything but the profile (see :func:`render`)."""

    data: bytes
    lines: list[bytes]
    sites: list[_Site]
    firmware: str
    bed: Bed
    park: tuple[float, float]
    retract_mm: float
    fw_retract: bool
    notes: list[str]


def render(plan: Plan, snapshot: SnapshotSettings) -> Prepared:
    """The prepared file for ``plan`` with ``snapshot``'s profile, lift, feeds and hold."""
    lines, fw, z_top = plan.lines, plan.firmware, plan.bed.max_z_mm
    cr = b"\r" if lines and lines[0].endswith(b"\r") else b""
    capped, prev = 0, 0
    out: list[bytes] = []
    for site in plan.sites:
        st = site.states[fw]
        if z_top is not None and st.pos[2] + snapshot.lift_mm > z_top + 1e-9:
            capped += 1
        out += lines[prev:site.at]
        block = _block(st, fw, site, snapshot, plan.park, z_top, plan.retract_mm, plan.fw_retract)
        out += [s.encode() + cr for s in block]
        prev = site.at
    out += lines[prev:]
    new = b"\n".join(out)
    if guess_relative_e(plan.data):  # make the assumed relative-E mode explicit for the firmware and re-parsing
        new = b"M83 ; layerwatch: this file's E values are relative" + cr + b"\n" + new
    notes = list(plan.notes)
    if capped:
        notes.append(f"{capped} block(s) lift less than {snapshot.lift_mm:g} mm: the bed's height is {z_top:g} mm")
    return Prepared(new, plan.bed, plan.park, fw, len(plan.sites), notes)


def _agreed_firmware(sites: list[_Site]) -> str:
    """With no firmware known, the modes at every block must be the same under all three rules."""
    for s in sites:
        keys = {(st.axis_rel, st.e_flag_rel or (f == KLIPPER and st.axis_rel), round(st.e, 6))
                for f, st in s.states.items()}
        if len(keys) > 1:
            raise ConfigError(
                f"at layer {s.layer} this file's extruder mode depends on the firmware (G90/G91 after M82/M83); "
                "pass --firmware marlin|klipper|reprap."
            )
    return FIRMWARES[0]


def insert_snapshots(data: bytes, snapshot: SnapshotSettings, printer: PrinterProfile | None = None, *,
                     bed: Bed | None = None, firmware: str | None = None) -> bytes:
    """G-code ``data`` with a snapshot block after every ``snapshot.every_n_layers``-th layer.

    Same as :func:`prepare_gcode` but returns only the bytes.
    """
    return prepare_gcode(data, snapshot, printer, bed=bed, firmware=firmware).data
