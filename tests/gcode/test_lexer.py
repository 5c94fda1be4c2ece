"""Lexer edge cases: comments, CRLF, N/checksums, lowercase, no spaces, extended commands."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.gcode import read_toolpath
from layerwatch.gcode.reader import run

SQUARE = "G1 X10 Y0 E1\nG1 X10 Y10 E2\nG1 X0 Y10 E3\nG1 X0 Y0 E4\n"


def ends(text: str | bytes) -> np.ndarray:
    data = text.encode() if isinstance(text, str) else text
    seg = run(data)[0]
    return seg[:, [2, 3, 5]]


def test_plain_square():
    np.testing.assert_allclose(ends(SQUARE), [[10, 0, 1], [10, 10, 1], [0, 10, 1], [0, 0, 1]])


@pytest.mark.parametrize(
    "variant",
    [
        SQUARE.replace("\n", "\r\n"),
        SQUARE.lower(),
        SQUARE.replace(" ", ""),
        "".join(f"N{i} {ln} *{i * 7 % 97}\n" for i, ln in enumerate(SQUARE.splitlines())),
        SQUARE.replace("\n", " ; a comment X99 E99\n"),
        SQUARE.replace(" Y", " (inline comment X5) Y"),
        SQUARE.replace("G1 ", "G01 ").replace(" E", "\tE"),
        "G1 X10 Y0 E+1.0\nG1 X10.000 Y10.0E2\nG1 X.0 Y10 E3.\nG1 X-0 Y0 E4\n",
    ],
    ids=["crlf", "lower", "nospace", "N-checksum", "semicolon", "paren", "G01-tab", "numbers"],
)
def test_variants_same_moves(variant):
    np.testing.assert_allclose(ends(variant), ends(SQUARE))


def test_modal_motion_without_G_word():
    np.testing.assert_allclose(ends("G1 X1 Y0 E1\nX2 E2\nY3 E3\n")[:, :2], [[1, 0], [2, 0], [2, 3]])


def test_strings_and_extended_commands_are_not_moves():
    text = (
        "G1 X10 Y0 E1\n"
        "M118 E1 layerwatch snapshot layer=3 z=0.6\n"
        "M117 X500 Y500 E900\n"
        "LAYERWATCH_SNAPSHOT LAYER=3 Z=0.600\n"
        "EXCLUDE_OBJECT_START NAME=cube_X5\n"
        "@layerwatch snapshot layer=3 z=0.6\n"
        "G1 X10 Y10 E2\n"
    )
    np.testing.assert_allclose(ends(text), [[10, 0, 1], [10, 10, 1]])
    stats = run(text.encode())[6]
    assert stats[6] >= 2  # unknown commands counted, not fatal


def test_line_numbers_of_segments():
    tp = read_toolpath(b"; header\n\nG1 X1 Y0 E1\r\n; c\nG1 X2 Y0 E2\n")
    assert tp.line.tolist() == [3, 5]


def test_tag_comments_found_in_same_pass():
    text = ";LAYER_CHANGE\n;Z:0.2\n;TYPE:External perimeter\nG1 Z0.2\nG1 X1 Y0 E1\n;TYPE:Solid infill\nG1 X2 Y0 E2\n"
    tp = read_toolpath(text.encode())
    assert tp.detection == "tags:prusaslicer"
    from layerwatch.gcode.toolpath import FEATURES

    assert [FEATURES[c] for c in tp.feature] == ["external_perimeter", "solid_infill"]


def test_no_trailing_newline_and_truncation_warning():
    tp = read_toolpath(b"G1 X1 Y0 E1\nG1 X2 Y0 E2\nG1 X3 Y")
    assert tp.n_segments == 2  # the cut line lost its E
    assert any("truncated" in w and ":3: 'G1 X3 Y'" in w for w in tp.warnings)
