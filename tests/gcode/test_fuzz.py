"""Never crash, bounded memory: malformed numbers, arcs, containers and truncated files are a
GcodeError (one line, exit 2) or a recorded warning, and no input makes the reader hold more
than 4x the file size + 200 MB (tracemalloc sees NumPy and numba-NRT buffers alike)."""

from __future__ import annotations

import tracemalloc
from functools import cache

import pytest
from gcode_refs import shared_gcode_files
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as hs

from layerwatch.errors import GcodeError
from layerwatch.gcode import read_toolpath

MB = 1_000_000
#: tokens that broke earlier readers (issue 20), spliced into real files
TOKENS = (
    b"E1.2.3", b"G1 X1.2.3 Y-.-5 E--1", b"G2 X10 Y10 I1e15 J0 E1", b"G3 X1 Y1 I1000000000000000 J1e16 E.5",
    b"G2 X0 Y0 R0 E1", b"G3 X5 Y5 R-0 E1", b"G2 X0 Y0 I0 J0 E1", b"G2 I99999 J99999 E1",
    b"M200 D0.0001", b"M200 D1.75", b"M221 S-5", b"M221 S100000", b"M221 T99 S50", b"G20", b"G91",
    b"G92 E1e308", b"T999999", b"N12 G1 X1*45", b"\x00\xff\xfe", b";LAYER:", b";LAYER_CHANGE",
    b";Z:1e999", b";layer:abc", b"; layer_height = 1.2.3", b"; filament_diameter = 9..1",
    b";FLAVOR:UltiGCode", b"9" * 400, b"G1 X" + b"9" * 400 + b" E1", b"\n" * 50, b"(", b";TYPE:",
)


@cache
def _seeds() -> tuple[bytes, ...]:
    """Every shared file; of the .bgcode containers only those under 64 kB (decoding a large one
    whole for each of 3,000 examples would blow the time budget; damage is damage at any size)."""
    paths = [p for p in shared_gcode_files() if p.suffix != ".bgcode" or p.stat().st_size < 65536]
    return tuple(p.read_bytes() for p in paths)


def _mutate(seed: bytes, start: int, length: int, edits: list[tuple[int, int, int]]) -> bytes:
    if seed[:4] == b"GCDE":  # containers: keep the header, damage bytes or cut the file
        data = bytearray(seed[: max(10, start % len(seed))] if length % 3 == 0 else seed)
    else:
        a = start % max(1, len(seed) - 1)
        data = bytearray(seed[a : a + length])
    for kind, pos, arg in edits:
        at = pos % (len(data) + 1)
        if kind == 0:
            data[at:at] = TOKENS[arg % len(TOKENS)] + b"\n"
        elif kind == 1 and data:
            data[min(at, len(data) - 1)] = arg % 256
        elif kind == 2:
            del data[at : at + arg % 64]
        else:
            data[at:at] = data[at : at + arg % 512]  # duplicate a stretch
    return bytes(data)


def _read_bounded(data: bytes) -> None:
    tracemalloc.start()
    try:
        read_toolpath(data)
    except GcodeError as exc:
        assert "\n" not in str(exc).strip(), str(exc)
    finally:
        _cur, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert peak <= 4 * len(data) + 200 * MB, (len(data), peak)


@pytest.mark.slow
@settings(max_examples=3000, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(
    which=hs.integers(0, 10_000),
    start=hs.integers(0, 10**7),
    length=hs.integers(0, 8_000),
    edits=hs.lists(hs.tuples(hs.integers(0, 3), hs.integers(0, 10**6), hs.integers(0, 10**4)), max_size=8),
)
def test_mutated_real_files_never_crash(which, start, length, edits):
    seeds = _seeds()
    if not seeds:
        pytest.skip("shared data absent")
    _read_bounded(_mutate(seeds[which % len(seeds)], start, length, edits))


@pytest.mark.parametrize(
    "text",
    [
        b"G1 X1 Y1 E1.2.3\nG1 X2 Y2 E2\n",  # no M82/M83: E guessed from malformed values
        b"; layer_height = 1.2.3\nM83\nG1 Z0.2\nG1 X1 Y1 E1\n",
        b"M83\nG1 Z0.2\nG2 X10 Y10 I1000000000000000 J0 E1\nG3 X0 Y0 I0 J1e15 E1\n",
        b"M83\nG1 Z0.2\nG2 X0 Y0 R0 E1\nG2 X0 Y0 I0 J0 E1\n",
        b"M83\nG1 Z0.2\nG1 X" + b"9" * 400 + b" Y1 E1\nG1 X1 Y1 E1\n",
        b"M83\nG1 Z0.2\nG1 X1 Y1 E1\nG1 X2 Y",  # truncated mid-move
    ],
    ids=["E1.2.3", "bad-header-number", "huge-IJ", "zero-radius", "400-digits", "truncated"],
)
def test_malformed_input_is_read_or_warned(text):
    tp = read_toolpath(text)
    assert all(w.startswith("<memory>") for w in tp.warnings)


def test_huge_radius_arcs_stay_small():
    """A 26 kB file of huge-radius extruding arcs (7.5 GB in the issue) stays within the bound."""
    lines = [b"G21", b"G90", b"M83", b"G1 Z0.2"]
    k = 0
    while sum(len(x) + 1 for x in lines) < 26_000:
        k += 1
        lines.append(b"G2 X%d Y%d I%d J%d E0.5" % (k % 200, (7 * k) % 200, 90_000 - k, k - 90_000))
    data = b"\n".join(lines) + b"\n"
    _read_bounded(data)
    tp = read_toolpath(data)
    assert any("fewer chords" in w or "absurd radius" in w for w in tp.warnings)


@pytest.mark.parametrize("cut", [10, 11, 20, 100, 1000, -7])
def test_damaged_bgcode_is_a_gcode_error(cut):
    seed = next((s for s in _seeds() if s[:4] == b"GCDE"), None)
    if seed is None:
        pytest.skip("shared data absent")
    bad = bytearray(seed[:cut])
    if len(bad) > 30:
        bad[14:18] = b"\xff\xff\xff\x7f"  # absurd block size
    with pytest.raises(GcodeError):
        read_toolpath(bytes(bad))


def test_malformed_numbers_are_a_warning_with_file_and_line(tmp_path):
    path = tmp_path / "bad.gcode"
    path.write_bytes(b"M83\nG1 Z0.2\nG1 X1 Y1 E1\nG1 X2 Y1 E1.2.3\nG1 X3 Y1 E--1\nG1 X4 Y1 E1\n")
    tp = read_toolpath(path)
    [w] = [w for w in tp.warnings if "malformed" in w]
    assert w.startswith("bad.gcode:4: 'G1 X2 Y1 E1.2.3': 2 line(s)")
    assert tp.n_segments == 3  # E1.2 read; E--1 has no number, so that move extrudes nothing
