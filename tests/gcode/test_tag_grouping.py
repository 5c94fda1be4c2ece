"""Tags are classified once per distinct comment; grouping is exact even when hashes collide."""

from __future__ import annotations

import numpy as np

from layerwatch.gcode import tags
from layerwatch.gcode.reader import kernel_outputs

GCODE = (
    b";LAYER:0\n;TYPE:SKIRT\nG1 X0 Y0 Z0.2\nG1 X1 Y0 E1\n;TYPE:WALL-OUTER\nG1 X2 Y0 E2\n"
    b";LAYER:1\n;Z:0.4\n;TYPE:SKIRT\nG1 X2 Y1 Z0.4 E3\n;TYPE:WALL-OUTER\r\nG1 X3 Y1 E4\n"
    b";TYPE:" + b"L" * 80 + b"a\nG1 X4 Y1 E5\n;TYPE:" + b"L" * 80 + b"b\nG1 X5 Y1 E6\n"
    b";LAYER:1\n;LAYER:2\n;TYPE:WALL-OUTER"
)


def _scan():
    return tags.decode_tags(GCODE, kernel_outputs(GCODE).cmt)


def test_equal_comments_share_one_classification_and_long_ones_are_read_whole():
    scan = _scan()
    assert scan.style == "cura"
    np.testing.assert_array_equal(scan.layer_lines, [1, 7, 18])  # the repeated ;LAYER:1 dropped
    skirt, outer = tags.feature_from_name("SKIRT"), tags.feature_from_name("WALL-OUTER")
    other = tags.feature_from_name("L" * 80 + "a")
    np.testing.assert_array_equal(scan.feature_codes, [skirt, outer, skirt, outer, other, other, outer])
    first, inverse, long = tags._distinct_comments(GCODE, kernel_outputs(GCODE).cmt[:, 0].copy())
    assert long.sum() == 2 and inverse[1] == inverse[5] and inverse[2] != inverse[6]  # CR kept apart


def test_grouping_stays_exact_when_every_hash_collides(monkeypatch):
    expected = _scan()
    monkeypatch.setattr(tags, "_row_hash", lambda keys, lengths: np.zeros(keys.shape[0], np.uint64))
    got = _scan()
    assert got.style == expected.style
    for field in ("layer_lines", "layer_z", "feature_lines", "feature_codes"):
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
