"""Compatibility names for the snapshot post-processor.

The block itself lives in :mod:`layerwatch.gcode.snapshot` (safe by
construction: bed, firmware rules, hold at the park spot), the bed in
:mod:`layerwatch.gcode.bed`, the checker in :mod:`layerwatch.gcode.firmware_model`
and the Klipper macros in :mod:`layerwatch.gcode.klipper_macros`.
"""

from __future__ import annotations

from layerwatch.gcode.klipper_macros import KLIPPER_MACRO
from layerwatch.gcode.snapshot import insert_snapshots, prepare_gcode, trigger_lines

__all__ = ["insert_snapshots", "prepare_gcode", "KLIPPER_MACRO", "trigger_lines"]
