"""Every shared slicer file x every snapshot profile x Marlin, Klipper and RepRapFirmware rules: 0 violations.

Each file is prepared for the firmware whose rules are checked, on the bed it states (or, when it
states none, a bed 20 mm around its print, as a user would pass with --bed), and run through
:func:`layerwatch.gcode.firmware_model.check_prepared`: every emitted move on the bed, E and every
mode restored after each block, parked and still at the trigger with a hold there, no tool change
or pin write, and the slicer's own moves (machine position and filament) exactly as before.
"""

from __future__ import annotations

import pytest
from gcode_refs import shared_gcode_files

from layerwatch.gcode import read_toolpath
from layerwatch.gcode.bed import bed_from_gcode, parse_bed
from layerwatch.gcode.firmware_model import FIRMWARES, check_prepared, slicer_trace
from layerwatch.gcode.reader import guess_relative_e, load_bytes
from layerwatch.gcode.settings import SnapshotSettings
from layerwatch.gcode.snapshot import PROFILES, plan_snapshots, render

FILES = shared_gcode_files()


def _bed(data: bytes):
    stated = bed_from_gcode(data)
    if stated is not None:
        return stated
    x0, y0, x1, y1 = read_toolpath(data).bounds
    return parse_bed(f"{x0 - 20},{y0 - 20};{x1 + 20},{y0 - 20};{x1 + 20},{y1 + 20};{x0 - 20},{y1 + 20}")


@pytest.mark.slow
@pytest.mark.parametrize("path", FILES, ids=[p.name for p in FILES])
def test_every_profile_and_firmware_is_safe(path):
    data, _ = load_bytes(path)
    if read_toolpath(data).n_layers == 0:
        pytest.skip("no printed layers (CNC file): nothing is inserted")
    bed = _bed(data)
    original = (b"M83\n" if guess_relative_e(data) else b"") + data
    found = {}
    for fw in FIRMWARES:
        plan = plan_snapshots(data, SnapshotSettings(), bed=bed, firmware=fw)  # the same sites for every profile
        trace = slicer_trace(original, fw)
        for profile in PROFILES:
            result = render(plan, SnapshotSettings(profile=profile))
            assert result.blocks > 0
            v = check_prepared(result.data, fw, bed, original=trace)
            if v:
                found[(fw, profile)] = v[:3]
    assert found == {}
