"""The Klipper macro file for the ``klipper`` snapshot profile (``layerwatch klipper-config``).

How the hold for the photo works on Klipper
-------------------------------------------
The prepared G-code (:mod:`layerwatch.gcode.snapshot`) retracts, lifts, parks
inside the bed the file was sliced for and runs ``M400``; then it calls

``LAYERWATCH_SNAPSHOT LAYER=<n> Z=<z>``
    ``M400``, clears ``taken`` and sends ``layerwatch snapshot layer=<n> z=<z>``
    with ``RESPOND``; Moonraker pushes it to layerwatch as a G-code response.
``LAYERWATCH_WAIT LAYER=<n> STEP=<k> OF=<N>`` (N lines, :func:`~layerwatch.gcode.snapshot.hold_steps`)
    Each step dwells :data:`~layerwatch.gcode.snapshot.HOLD_STEP_S` (``G4`` + ``M400``)
    unless the host has confirmed the frame. The host confirms by sending
    :func:`ack_script` (``SET_GCODE_VARIABLE MACRO=LAYERWATCH_SNAPSHOT VARIABLE=taken
    VALUE=<n>``) through Moonraker's ``/printer/gcode/script``.

The wait is unrolled into separate file lines on purpose: Klipper renders a
macro's template once, before running it, and keeps the G-code mutex for the
whole macro, so a host command could not get in while one macro loops. Between
two lines of a file printed from the virtual SD card Klippy lets waiting
commands run, and each step is rendered afresh, so it sees the host's answer.
A dead host costs at most ``N * HOLD_STEP_S`` per layer (``prepare --hold``);
after three layers in a row without an answer only the first step of each
layer waits, until the host answers again. The print is never paused.

Parking stays in the prepared G-code (not in the macro) so that the same
machine model (:mod:`layerwatch.gcode.firmware_model`) checks it for every
firmware, and so that the park spot comes from the bed the file was sliced
for; Klipper's own ``position_min``/``position_max`` check every move again.
"""

from __future__ import annotations

from layerwatch.gcode.snapshot import HOLD_STEP_S

__all__ = ["klipper_config", "KLIPPER_MACRO", "ack_script"]

_STEP_MS = int(round(HOLD_STEP_S * 1000))


def klipper_config(version: str = "") -> str:
    """Text of ``layerwatch.cfg``: ``[respond]`` and the two macros, ready for ``[include layerwatch.cfg]``."""
    head = f"# layerwatch.cfg, written by `layerwatch klipper-config`{f' (layerwatch {version})' if version else ''}.\n"
    return head + f"""\
# Add `[include layerwatch.cfg]` to printer.cfg, then print files prepared with
#   layerwatch gcode prepare FILE --profile klipper -o FILE.layerwatch.gcode
# The prepared block parks the head inside the bed and calls LAYERWATCH_SNAPSHOT, then up to
# `--hold` seconds of LAYERWATCH_WAIT steps ({HOLD_STEP_S:g} s each) that end as soon as layerwatch sends
#   SET_GCODE_VARIABLE MACRO=LAYERWATCH_SNAPSHOT VARIABLE=taken VALUE=<layer>
# A dead host never stalls the print longer than that; after 3 unanswered layers only one step waits.

[respond]

[gcode_macro LAYERWATCH_SNAPSHOT]
description: layerwatch: the head is parked; announce the layer so the host takes its photo
variable_taken: -1
variable_misses: 0
gcode:
  {{% set layer = params.LAYER|default(-1)|int %}}
  {{% set z = params.Z|default(-1)|float %}}
  M400
  SET_GCODE_VARIABLE MACRO=LAYERWATCH_SNAPSHOT VARIABLE=taken VALUE=-1
  RESPOND MSG="layerwatch snapshot layer={{layer}} z={{'%.3f' % z}}"

[gcode_macro LAYERWATCH_WAIT]
description: layerwatch: one bounded step of the hold for the photo (nothing once the host has the frame)
gcode:
  {{% set layer = params.LAYER|default(-1)|int %}}
  {{% set step = params.STEP|default(0)|int %}}
  {{% set of = params.OF|default(1)|int %}}
  {{% set snap = printer["gcode_macro LAYERWATCH_SNAPSHOT"] %}}
  {{% if snap.taken == layer %}}
    {{% if snap.misses > 0 %}}
      SET_GCODE_VARIABLE MACRO=LAYERWATCH_SNAPSHOT VARIABLE=misses VALUE=0
    {{% endif %}}
  {{% elif snap.misses < 3 or step == 0 %}}
    G4 P{_STEP_MS}
    M400
    {{% if step == of - 1 %}}
      SET_GCODE_VARIABLE MACRO=LAYERWATCH_SNAPSHOT VARIABLE=misses VALUE={{snap.misses + 1}}
    {{% endif %}}
  {{% endif %}}
"""


#: the macro file without a version line (what ``klipper-config`` prints, minus its first line)
KLIPPER_MACRO = klipper_config().split("\n", 1)[1]


def ack_script(layer: int) -> str:
    """The G-code the host sends (Moonraker ``/printer/gcode/script``) once it has the frame of ``layer``."""
    return f"SET_GCODE_VARIABLE MACRO=LAYERWATCH_SNAPSHOT VARIABLE=taken VALUE={int(layer)}"
