"""Modal machine: arcs against analytic lengths, G91, M83, G92, G20, G28, tools, M101/M103."""

from __future__ import annotations

import math

import numpy as np
import pytest

from layerwatch.gcode import read_toolpath
from layerwatch.gcode.reader import CHORD_TOL_MM, run


def segs(text: str) -> np.ndarray:
    return run(text.encode())[0]


def arc_length(seg: np.ndarray) -> float:
    return float(np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]).sum())


@pytest.mark.parametrize(
    "text,length",
    [
        ("G1 X10 Y0 F600\nG3 X0 Y10 I-10 J0 E5\n", math.pi * 10 / 2),  # CCW quarter
        ("G1 X10 Y0\nG2 X0 Y10 I-10 J0 E5\n", 3 * math.pi * 10 / 2),  # CW three quarters
        ("G1 X10 Y0\nG3 X10 Y0 I-10 J0 E5\n", 2 * math.pi * 10),  # full circle
        ("G1 X10 Y0\nG3 X0 Y10 R10 E5\n", math.pi * 10 / 2),  # R form, short arc
        ("G1 X10 Y0\nG3 X0 Y10 R-10 E5\n", 3 * math.pi * 10 / 2),  # R<0: long arc
        ("G1 X5 Y0\ng2x-5y0i-5j0e3\n", math.pi * 5),  # half circle, lowercase
    ],
)
def test_arc_lengths_analytic(text, length):
    s = segs(text)
    # chord error bound: polygon inscribed in the circle
    assert arc_length(s) == pytest.approx(length, rel=2e-3)
    assert arc_length(s) <= length + 1e-9
    r = float(np.hypot(s[0, 0], s[0, 1])) if "X5" not in text else 5.0
    mid = (s[:, :2] + s[:, 2:4]) / 2
    sag = r - np.hypot(mid[:, 0], mid[:, 1])
    assert sag.max() <= CHORD_TOL_MM + 1e-9
    assert s[:, 5].sum() == pytest.approx(float(text.upper().split("E")[-1]), rel=1e-12)


def test_arc_direction_ccw_goes_through_positive_quadrant():
    s = segs("G1 X10 Y0\nG3 X0 Y10 I-10 J0 E5\n")
    assert (s[:, 2] >= -1e-9).all() and (s[:, 3] >= -1e-9).all()
    s = segs("G1 X10 Y0\nG2 X0 Y10 I-10 J0 E5\n")
    assert (s[:, 3] < -1).any()  # went round through negative Y


def test_helical_arc_interpolates_z():
    s = segs("G1 X10 Y0 Z1\nG3 X-10 Y0 Z2 I-10 J0 E5\n")
    assert s[0, 4] > 1 and s[-1, 4] == pytest.approx(2)


def test_g91_relative_moves_and_e():
    s = segs("G91\nG1 X10 Y0 E1\nG1 X0 Y10 E1\n")
    np.testing.assert_allclose(s[:, [2, 3, 5]], [[10, 0, 1], [10, 10, 1]])


def test_m83_relative_e_with_absolute_xyz():
    s = segs("G90\nM83\nG1 X10 Y0 E1\nG1 X20 Y0 E1\nG1 X30 Y0 E-2\nG1 X40 Y0 E1\n")
    np.testing.assert_allclose(s[:, [2, 5]], [[10, 1], [20, 1], [40, 1]])


def test_m82_absolute_e_with_g92_reset():
    s = segs("M82\nG1 X10 Y0 E5\nG92 E0\nG1 X20 Y0 E1\nG1 X30 Y0 E0.5\nG1 X40 Y0 E2\n")
    # E0.5 after E1 is a retract while moving: travel, not extrusion
    np.testing.assert_allclose(s[:, [2, 5]], [[10, 5], [20, 1], [40, 1.5]])


def test_g92_axis_offset_keeps_physical_position():
    s = segs("G1 X10 Y10\nG92 X0 Y0\nG1 X5 Y0 E1\n")
    np.testing.assert_allclose(s[0, :4], [10, 10, 15, 10])


def test_g20_inches():
    s = segs("G20\nG1 X1 Y0 E0.1\nG21\nG1 X50.8 Y0 E3\n")
    np.testing.assert_allclose(s[:, [2, 5]], [[25.4, 2.54], [50.8, 0.46]], atol=1e-9)


def test_g28_homes_to_zero():
    s = segs("G1 X50 Y50\nG92 X0\nG28 X\nG1 X10 Y50 E1\n")
    np.testing.assert_allclose(s[0, :4], [0, 50, 10, 50])


def test_tools_recorded():
    tp = read_toolpath(b"T0\nG1 X1 Y0 E1\nT1\nG1 X2 Y0 E2\n")
    assert tp.tool.tolist() == [0, 1]


def test_firmware_retraction_is_not_extrusion():
    s = segs("G1 X1 Y0 E1\nG10\nG1 X50 Y0\nG11\nG1 X51 Y0 E2\n")
    np.testing.assert_allclose(s[:, [2, 5]], [[1, 1], [51, 1]])


def test_m101_tool_on_dialect():
    s = segs("M101\nG1 X1 Y0\nG1 X2 Y0\nM103\nG1 X3 Y0\n")
    assert s.shape[0] == 2


def test_probe_state_records_modes():
    text = "G91\nM83\nT2\nG1 X1 Y1 F1200\nG20\n; here\n"
    state = run(text.encode(), np.array([6], np.int64))[5][0]
    lx, ly, lz, ox, oy, oz, e, feed, abs_xyz, e_rel, tool, inch, tool_on = state
    assert (lx, ly, feed, abs_xyz, e_rel, tool, inch) == (1, 1, 1200, 0, 1, 2, 1)


def test_axis_words_of_non_motion_g_codes_do_not_move():
    s = segs("G1 X1 Y1\nG29 P9 X10 Y-4 W32 H4\nG4 P500\nG10 P1 X5\nG1 X2 Y1 E1\n")
    np.testing.assert_allclose(s[:, :4], [[1, 1, 2, 1]])
