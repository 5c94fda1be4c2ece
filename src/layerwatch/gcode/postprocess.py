"""Insert a snapshot block after every (Nth) layer of a G-code file.

The block follows the paper's Table 1: wait for moves (``M400``), relative
mode, retract, lift Z, park XY out of the camera's view, optional light /
indicator, the snapshot *trigger* (carrying layer index and Z), return,
dwell (``G4 P500``), then restore the exact modal state the slicer had set
(G90/G91, M82/M83, G20/G21, tool, feedrate). The block never moves below
the part and never leaves the printer's volume. Extrusion is balanced
(retract then prime the same length), so re-parsing the output gives the
same layers and the same per-layer extrusion as the input.

Trigger profiles (``SnapshotSettings.profile``):

- ``octoprint``: ``@layerwatch snapshot layer=<n> z=<z>`` (host command) and
  ``M118 E1 layerwatch snapshot layer=<n> z=<z>`` (echoed by the firmware).
- ``klipper``: ``LAYERWATCH_SNAPSHOT LAYER=<n> Z=<z>`` (see :data:`KLIPPER_MACRO`).
- ``timelapse``: ``RESPOND MSG=...`` then moonraker-timelapse's ``TIMELAPSE_TAKE_FRAME``.
- ``m240``: ``M118`` line then ``M240`` (trigger camera).
- ``paper``: light platform on tool ``T1`` and an ``M42`` indicator pin
  around an ``M118`` trigger (delta printer set-up of the paper).

References
----------
Paper, Table 1 (G-code inserted after each layer).
"""

from __future__ import annotations

import numpy as np

from layerwatch.gcode.reader import guess_relative_e, read_toolpath, run
from layerwatch.gcode.settings import PrinterProfile, SnapshotSettings

__all__ = ["insert_snapshots", "KLIPPER_MACRO", "trigger_lines", "snapshot_block"]

#: Paste into printer.cfg (needs ``[respond]``) for the ``klipper`` profile.
KLIPPER_MACRO = """\
[respond]

[gcode_macro LAYERWATCH_SNAPSHOT]
description: Tell layerwatch that a layer is done (inserted by `layerwatch gcode prepare`)
gcode:
  {% set layer = params.LAYER|default(-1)|int %}
  {% set z = params.Z|default(-1)|float %}
  RESPOND MSG="layerwatch snapshot layer={layer} z={'%.3f' % z}"
"""


def _f(v: float) -> str:
    s = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def trigger_lines(profile: str, layer: int, z: float, snapshot: SnapshotSettings) -> list[str]:
    """The trigger lines of ``profile`` for ``layer`` at height ``z`` (mm)."""
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
        pin = snapshot.indicator_pin
        return [
            f"T{snapshot.light_tool} ; light platform on",
            f"M42 P{pin} S255 ; indicator on",
            f"M118 E1 {msg}",
            f"M42 P{pin} S0 ; indicator off",
        ]
    raise ValueError(f"unknown snapshot profile {profile!r}")


def snapshot_block(
    state: np.ndarray, layer: int, z: float, snapshot: SnapshotSettings, printer: PrinterProfile
) -> list[str]:
    """G-code lines of one snapshot block.

    Parameters
    ----------
    state : ndarray, shape (13,), float64
        Modal state before the block (see ``kernel.N_PROBE``): logical x, y, z,
        offsets x, y, z, e, feed (mm/min), abs_xyz, e_rel, tool, inch, tool-on (M101).
    layer, z : int, float
        Layer just finished and its Z (mm), written into the trigger.
    """
    lx, ly, lz, ox, oy, oz, _e, feed, abs_xyz, e_rel, tool, inch, tool_on = state.tolist()
    lo, hi = np.asarray(printer.volume_min_mm), np.asarray(printer.volume_max_mm)
    pz = lz + oz
    park = snapshot.park_xy_mm if snapshot.park_xy_mm is not None else (hi[0], hi[1])
    park_x = float(np.clip(park[0], lo[0], hi[0])) - ox
    park_y = float(np.clip(park[1], lo[1], hi[1])) - oy
    lift = float(min(max(pz + snapshot.lift_mm, pz), max(hi[2], pz))) - pz
    tf, rf, r = _f(snapshot.travel_feed_mm_min), _f(snapshot.retract_feed_mm_min), snapshot.retract_mm
    out = [f"; layerwatch snapshot block: layer {layer} z={z:.3f}", "M400", "G21", "G91", "M83"]
    if tool_on:
        out.append("M103")
    if r > 0:
        out.append(f"G1 E-{_f(r)} F{rf}")
    if lift > 0:
        out.append(f"G1 Z{_f(lift)} F{tf}")
    out += ["G90", f"G1 X{_f(park_x)} Y{_f(park_y)} F{tf}", "M400"]
    out += trigger_lines(snapshot.profile, layer, z, snapshot)
    if snapshot.profile == "paper":
        out.append(f"T{int(tool)} ; light platform off, back to the print tool")
    out.append(f"G1 X{_f(lx)} Y{_f(ly)} F{tf}")
    if lift > 0:
        out.append(f"G1 Z{_f(lz)} F{tf}")
    if r > 0:
        out.append(f"G1 E{_f(r)} F{rf}")
    out.append(f"G4 P{snapshot.settle_ms}")
    # restore the slicer's modal state exactly
    out.append("G20" if inch else "G21")
    out.append("G90" if abs_xyz else "G91")
    out.append("M83" if e_rel else "M82")
    if snapshot.profile != "paper" and int(tool) != 0:
        out.append(f"T{int(tool)}")
    if tool_on:
        out.append("M101")
    if feed > 0:
        out.append(f"G1 F{_f(feed / 25.4 if inch else feed)}")
    out.append("; layerwatch snapshot block end")
    return out


def insert_snapshots(data: bytes, snapshot: SnapshotSettings, printer: PrinterProfile) -> bytes:
    """G-code ``data`` with a snapshot block after every ``snapshot.every_n_layers``-th layer.

    The last layer always gets a block. Each block sits right after the last
    extruding move of its layer, before the slicer's layer-change code.

    Parameters
    ----------
    data : bytes
        ASCII G-code.
    snapshot : SnapshotSettings
        Profile, period, retract/lift/park distances, feeds, dwell.
    printer : PrinterProfile
        Build volume used to clamp the park position and the lift.

    Returns
    -------
    bytes
        The new G-code (same line endings as the input's first line).
    """
    tp = read_toolpath(data)
    n = snapshot.every_n_layers
    chosen = [lay for lay in tp.layers if (lay.index + 1) % n == 0 or lay.index == tp.n_layers - 1]
    if not chosen:
        return bytes(data)
    at = np.array([int(tp.line[lay.seg_stop - 1]) + 1 for lay in chosen], np.int64)
    probe_state = run(data, at)[5]
    nl = b"\r\n" if data[: data.find(b"\n") + 1].endswith(b"\r\n") else b"\n"
    ends = np.flatnonzero(np.frombuffer(data, np.uint8) == 10)
    parts: list[bytes] = []
    prev = 0
    for k, lay in enumerate(chosen):
        line = int(at[k])  # insert before this 1-based line
        off = int(ends[line - 2]) + 1 if line - 2 < len(ends) else len(data)
        parts.append(data[prev:off])
        if off == len(data) and not data.endswith(b"\n"):
            parts.append(nl)
        block = snapshot_block(probe_state[k], lay.index, lay.z, snapshot, printer)
        parts.append(nl.join(s.encode() for s in block) + nl)
        prev = off
    parts.append(data[prev:])
    if guess_relative_e(data):  # make the assumed relative-E mode explicit for the firmware and re-parsing
        parts.insert(0, b"M83 ; layerwatch: this file's E values are relative" + nl)
    return b"".join(parts)
