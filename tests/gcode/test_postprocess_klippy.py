"""The real Klippy (batch mode, cartesian, axis limits from the file's bed) accepts prepared files,
rejects an out-of-bed park with "Move out of range", and runs layerwatch's hold macros.

See :mod:`klippy_batch` for the printer and the MCU dictionary. Skipped without the Klippy venv,
failed under ``CI=true``.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from gcode_refs import shared_gcode_files
from klippy_batch import require_klippy, run_klippy

from layerwatch.gcode.bed import bed_from_gcode, parse_bed
from layerwatch.gcode.firmware_model import KLIPPER, slicer_trace
from layerwatch.gcode.settings import SnapshotSettings
from layerwatch.gcode.snapshot import plan_snapshots, render

FILES = {p.name: p for p in shared_gcode_files()}
#: Ender-3 V2 (marlin2 and marlin), a Voron in Klipper flavour, and Cura for a 300 mm Voron-like bed
CASES = {"prusaslicer-2.7.4_arc-fitting_zhop.gcode": None, "prusaslicer-2.7.4_spiral-vase.gcode": None,
         "superslicer-2.3.56_arcwelder.gcode": None, "cura-4.10.0_m83_multi-object.gcode": "300x300x300"}

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not FILES, reason="shared data absent")]


def _plan(name, hold_s=1.0):
    data = FILES[name].read_bytes()
    bed = parse_bed(CASES[name]) if CASES[name] else bed_from_gcode(data)
    plan = plan_snapshots(data, SnapshotSettings(profile="klipper", hold_s=hold_s), bed=bed, firmware=KLIPPER)
    tr = np.array(slicer_trace(data, KLIPPER))
    box = (tr[:, 0].min(), tr[:, 1].min(), tr[:, 0].max(), tr[:, 1].max(), tr[:, 2].max())
    return plan, box


def _print_time(log: str) -> float:
    return float(re.findall(r"Exiting \(print time ([\d.]+)s\)", log)[-1])


@pytest.mark.parametrize("name", list(CASES))
def test_klippy_accepts_prepared_file(name, tmp_path):
    require_klippy()
    plan, box = _plan(name)
    prepared = render(plan, SnapshotSettings(profile="klipper", hold_s=1.0))
    run = run_klippy(prepared.data, plan.bed, tmp_path, box)
    log = (tmp_path / "klippy.log").read_text()
    assert run.returncode == 0 and "!! " not in run.stdout, log[-2000:]
    assert "Move out of range" not in log and "Exiting (print time" in log
    assert prepared.data.count(b"LAYERWATCH_SNAPSHOT LAYER=") == prepared.blocks > 0


def test_klippy_rejects_a_park_off_the_bed(tmp_path):
    require_klippy()
    name = "prusaslicer-2.7.4_arc-fitting_zhop.gcode"
    plan, box = _plan(name)
    plan.park = (max(box[2], plan.bed.bounds[2]) + 20.0, plan.park[1])  # what prepare refuses to write
    bad = render(plan, SnapshotSettings(profile="klipper", hold_s=1.0))
    run = run_klippy(bad.data, plan.bed, tmp_path, box)
    log = (tmp_path / "klippy.log").read_text()
    assert run.returncode != 0 and "Move out of range" in log


def test_klippy_hold_is_bounded_when_the_host_never_answers(tmp_path):
    """No host confirms a frame: each LAYERWATCH_WAIT step dwells 0.5 s; 3 layers wait the whole hold (2 steps),
    then only one step per layer. 13 layers: 3 * 1.0 + 10 * 0.5 = 8.0 s more print time than without the steps."""
    require_klippy()
    name = "prusaslicer-2.7.4_arc-fitting_zhop.gcode"
    plan, box = _plan(name, hold_s=1.0)
    held = render(plan, SnapshotSettings(profile="klipper", hold_s=1.0)).data
    assert len(plan.sites) == 13
    bare = re.sub(rb"(?m)^LAYERWATCH_WAIT [^\n]*\n", b"", held)
    run_klippy(held, plan.bed, tmp_path / "held", box)
    run_klippy(bare, plan.bed, tmp_path / "bare", box)
    t_held = _print_time((tmp_path / "held" / "klippy.log").read_text())
    t_bare = _print_time((tmp_path / "bare" / "klippy.log").read_text())
    assert t_held - t_bare == pytest.approx(8.0, abs=0.05)
