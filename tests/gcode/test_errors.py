"""Bad input: clear GcodeError or warnings, never an unhandled exception (incl. hypothesis)."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from layerwatch.errors import GcodeError, LayerwatchError
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.bgcode import decode_bgcode


def test_empty_file(tmp_path):
    p = tmp_path / "empty.gcode"
    p.write_bytes(b"  \n\n")
    with pytest.raises(GcodeError, match=r"empty\.gcode: the file is empty"):
        read_toolpath(p)


def test_missing_file(tmp_path):
    with pytest.raises(GcodeError, match="no such G-code file"):
        read_toolpath(tmp_path / "nope.gcode")


def test_binary_junk(tmp_path):
    p = tmp_path / "junk.gcode"
    p.write_bytes(bytes(range(256)) * 50)
    with pytest.raises(GcodeError, match=r"junk\.gcode: binary data .* export ASCII G-code"):
        read_toolpath(p)


def test_non_text_lines_warned_with_line():
    tp = read_toolpath(b"G1 X1 Y0 E1\nG1 X2 \xff\xfe Y0 E2\nG1 X3 Y0 E3\n")
    assert tp.n_segments == 3
    assert any("<memory>:2: 'G1 X2" in w and "non-text" in w for w in tp.warnings)


def test_no_extrusion_warns():
    tp = read_toolpath(b"G28\nG1 X10 Y10 F3000\nM84\n")
    assert tp.n_layers == 0 and any("no extruding moves" in w for w in tp.warnings)


def test_absurd_coordinates_warned():
    tp = read_toolpath(b"G1 X1 Y0 E1\nG1 X1e9 Y0 E2\nG1 X900000 Y0 E3\n")
    assert any(":3: 'G1 X900000 Y0 E3'" in w and "absurd" in w for w in tp.warnings)


def test_arc_without_centre_warned():
    tp = read_toolpath(b"G1 X1 Y0 E1\nG2 X5 Y5 E2\n")
    assert any(":2: 'G2 X5 Y5 E2'" in w and "arc" in w for w in tp.warnings)


def test_bgcode_bad_header_and_truncated():
    with pytest.raises(GcodeError, match="not a binary G-code"):
        decode_bgcode(b"GCDX0000000000")
    with pytest.raises(GcodeError, match="truncated"):
        decode_bgcode(b"GCDE\x01\x00\x00\x00\x01\x00\x01\x00")


WORDS = st.sampled_from(
    ["G0", "G1", "G2", "G3", "G90", "G91", "G92", "M82", "M83", "G20", "G21", "G28", "G10", "G11",
     "T1", "M101", "M103", "X", "Y", "Z", "E", "F", "I", "J", "R", "N", "*", ";", "(", ")", " ",
     "\n", "\r\n", "-", ".", "1", "0.5", "12.7", "-3", ";LAYER:", ";LAYER_CHANGE\n", ";Z:", "; layer 1, Z = ",
     "M118 ", "@", "LAYERWATCH_SNAPSHOT ", "\t", "e", "x", "\xff"]
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(WORDS, max_size=80))
def test_random_gcode_never_crashes(words):
    data = "".join(words).encode("latin-1")
    try:
        tp = read_toolpath(data)
    except LayerwatchError:
        return
    assert sum(lay.n_segments for lay in tp.layers) == tp.n_segments


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_mutated_real_gcode_never_crashes(data):
    base = bytearray(
        b";LAYER_CHANGE\n;Z:0.2\nG90\nM82\nG1 Z0.2 F600\nG1 X0 Y0\nG1 X10 Y0 E1\nG2 X10 Y10 I0 J5 E2\n"
        b";TYPE:Perimeter\nG92 E0\nG1 X0 Y10 E1 ; c\n;LAYER_CHANGE\n;Z:0.4\nG1 Z0.4\nG1 X5 Y5 E2\n"
    )
    for _ in range(data.draw(st.integers(1, 8))):
        op = data.draw(st.sampled_from(["flip", "cut", "dup", "insert"]))
        i = data.draw(st.integers(0, max(len(base) - 1, 0)))
        if op == "flip" and base:
            base[i] = data.draw(st.integers(0, 255))
        elif op == "cut":
            del base[i:]
        elif op == "dup":
            base[i:i] = base[i : i + data.draw(st.integers(1, 20))]
        else:
            base[i:i] = data.draw(st.binary(max_size=6))
    try:
        read_toolpath(bytes(base))
    except LayerwatchError:
        pass


def test_bgcode_unknown_compression_refused():
    import struct

    block = struct.pack("<HHII", 1, 9, 10, 4) + b"\x00\x00" + b"abcd" + b"\x00" * 4
    data = b"GCDE" + struct.pack("<IH", 1, 1) + block
    with pytest.raises(GcodeError, match="export ASCII G-code"):
        read_toolpath(data)


def test_heatshrink_round_trip_against_reference_encoder():
    """A tiny independent LZSS encoder (literals + one back-reference) decoded by our decoder."""
    from layerwatch.gcode.bgcode_codecs import heatshrink_decode, meatpack_decode

    bits = []
    for ch in b"G1 X":
        bits += [1] + [int(b) for b in f"{ch:08b}"]
    bits += [0] + [int(b) for b in f"{3:011b}"] + [int(b) for b in f"{7:04b}"]  # copy 8 from 4 back
    bits += [0] * (-len(bits) % 8)
    src = bytes(int("".join(map(str, bits[i : i + 8])), 2) for i in range(0, len(bits), 8))
    assert heatshrink_decode(src, 12, 11, 4) == b"G1 XG1 XG1 X"
    # MeatPack: enable packing; 'G1' in one byte (low nibble first); full-width 'Z' before its
    # packed partner '5'; '\n' ends the line (its high nibble is padding)
    packed = bytes([0xFF, 0xFF, 251, 0x1D, 0x5F, ord("Z"), 0x0C])
    assert meatpack_decode(packed) == b"G1Z5\n"
