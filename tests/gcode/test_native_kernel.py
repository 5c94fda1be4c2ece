"""The compiled kernel (``_ckernel.c``, built by ``pip install``) and the numba kernel agree
bit for bit, and a compiled module built from another source is not used."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from layerwatch.gcode import kernel_abi, native, read_toolpath
from layerwatch.gcode.reader import CHORD_TOL_MM, guess_relative_e, load_bytes

SHARED = Path(os.environ.get("LAYERWATCH_SHARED_DATA", Path(__file__).resolve().parents[2].parent / "shared" / "data"))
CORPUS = sorted((SHARED / "gcode").glob("*")) if (SHARED / "gcode").is_dir() else []
built = pytest.mark.skipif(native.compiled_module() is None, reason="compiled kernel not built (pip install -e .)")

#: inputs that reach every branch of the machine: arcs (I/J, R, bad, huge), G20, G91, G92, M82/M83,
#: M101/M103, M200 D, M221 with and without T (and T beyond the 16 flow slots), Klipper macros,
#: bad bytes, malformed numbers, checksums, parentheses, no final newline
EDGES = [
    b"G21\nG90\nM82\nG92 E0\nG1 X10 Y10 Z0.2 F1200\nG1 X20 Y10 E1.5\nG2 X30 Y20 I5 J5 E2\nG3 X10 Y10 R-12 E3\n"
    b"G2 X10 Y10 I1e16 J0 E4\nG3 X0 Y0 E5\nG2 X5 Y5 R1 E6\n",
    b"M83\nG91\nG1 X1 Y1 E0.1\nG90\nG1 X5 Y5 E0.2 ; comment\n(paren (nested) comment) G1 X9\n*12\nN10 G1 X3 Y3 E0.1*77\n",
    b"M83\nG20\nG1 X1 Y1 Z0.01 E0.1\nG21\nM221 S95\nG1 X1.5 Y1.5 E0.5\nM221 S50 T1\nT1\nG1 X2 Y2 E1\n"
    b"T20\nM221 S80\nG1 X3 Y3 E1\nG1 E5\nG1 E-1\nG1 E1\n",
    b"M101\nG1 X1 Y1 Z0.2\nM103\nG1 X2 Y2\nM200 D1.75\nG1 X3 Y3 E2\nM200 D0\nG1 X4 Y4 E3\n",
    b"PRINT_START BED=60\nG1 X1 Y1 E1.2.3\nG1 X--1 Y2 E%\nG1 X\xff2 Y3 E1\nG28 X\nG92\nG10\nG11\nG4 P100\nG1 X1e300 Y0 E1",
    b";LAYER:0\n;TYPE:SKIRT\nG1 X0 Y0 Z0.3\nG1 X10 Y0 E1\nG2 X10 Y0 I-5 J0 E5\n;LAYER:1\nG1 Z0.6\nG3 X0 Y0 R5 E6\n",
]


def _mutations(data: bytes, n: int, seed: int) -> list[bytes]:
    """``n`` damaged copies of ``data``: bytes flipped, lines cut or repeated."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        b = bytearray(data[: 20000])
        for _ in range(int(rng.integers(1, 30))):
            i = int(rng.integers(0, len(b)))
            b[i] = int(rng.choice([0x2E, 0x2D, 0x45, 0x47, 0x20, 0x0A, 0x3B, 0x58, 0x39, 0xFF]))
        out.append(bytes(b))
    return out


def _assert_same(data: bytes, probes: np.ndarray | None = None) -> None:
    probes = np.unique(np.linspace(1, data.count(b"\n") + 2, 40).astype(np.int64)) if probes is None else probes
    args = (data, probes, CHORD_TOL_MM, guess_relative_e(data), 0.0)
    a, b = native.run_kernel(*args, use="numba"), native.run_kernel(*args, use="c")
    for name, x, y in zip(a._fields, a, b, strict=True):
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
        assert y.flags.c_contiguous and y.flags.writeable, name


@built
@pytest.mark.slow
@pytest.mark.parametrize("path", CORPUS, ids=lambda p: p.name)
def test_compiled_and_numba_kernels_agree_on_every_corpus_file(path):
    data, _ = load_bytes(path)
    _assert_same(data)


@built
@pytest.mark.slow
def test_compiled_and_numba_kernels_agree_on_edge_cases_and_damaged_files():
    for data in EDGES:
        _assert_same(data)
    _assert_same(EDGES[0], np.zeros(0, np.int64))
    _assert_same(b"G1 X1 Y1 E1\nG1 X2 Y2 E2\n", np.arange(1, 4, dtype=np.int64))
    seeds = [p for p in CORPUS if p.suffix != ".bgcode"][:6]
    for k, path in enumerate(seeds):
        for data in _mutations(path.read_bytes(), 25, k):
            _assert_same(data)


@built
def test_the_compiled_kernel_uses_the_numba_kernels_slots_and_limits():
    abi = native.compiled_module().ABI
    assert abi and all(getattr(kernel_abi, k) == v for k, v in abi.items()), abi


@built
def test_read_toolpath_is_the_same_with_either_kernel(monkeypatch):
    sample = CORPUS[0] if CORPUS else None
    data = sample.read_bytes() if sample else EDGES[5]
    tp_c = read_toolpath(data)
    monkeypatch.setattr(native, "_C", None)
    assert native.backend() == "numba"
    tp_n = read_toolpath(data)
    for field in ("start", "end", "z", "e", "width", "feature", "tool", "line"):
        np.testing.assert_array_equal(getattr(tp_c, field), getattr(tp_n, field), err_msg=field)
    assert tp_c.layers == tp_n.layers and tp_c.warnings == tp_n.warnings


@built
def test_a_module_built_from_another_source_is_not_used(tmp_path):
    source = Path(native.__file__).with_name("_ckernel.c")
    same, edited = tmp_path / "same.c", tmp_path / "edited.c"
    same.write_bytes(source.read_bytes())
    edited.write_bytes(source.read_bytes() + b"/* edited */\n")
    assert native.compiled_module(same) is not None
    assert native.compiled_module(edited) is None  # the build's key names other source bytes
    assert native.compiled_module(same).SOURCE_KEY == native.source_key(source)


def test_without_the_compiled_module_the_numba_kernel_runs(monkeypatch):
    monkeypatch.setenv("LAYERWATCH_GCODE_KERNEL", "numba")
    assert native.compiled_module() is None
    monkeypatch.setattr(native, "_C", None)
    tp = read_toolpath(EDGES[5])
    assert tp.n_layers == 2 and native.backend() == "numba"


@built
def test_gcode_info_does_not_import_numba(tmp_path):
    """The compiled kernel spares `gcode info` numba's import and cache load (most of a cold start)."""
    gcode = tmp_path / "part.gcode"
    gcode.write_bytes(EDGES[5])
    code = ("import sys, io, contextlib\nfrom layerwatch.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            f"    assert main(['gcode', 'info', {str(gcode)!r}]) == 0\n"
            "print('numba' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
