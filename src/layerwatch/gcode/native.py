"""The G-code kernel to run: the ahead-of-time compiled one when built, else numba's.

``pip install`` compiles ``_ckernel.c`` (setup.py; optional, so a machine without a C
compiler still installs). That module starts in milliseconds, where importing numba and
loading the cached numba kernel takes about a second, which is most of a cold
``layerwatch gcode info``. Both kernels give identical outputs
(``tests/gcode/test_native_kernel.py``).

A compiled module is used only when it was built from the C source beside it: the build
compiles the source's SHA-256 in (``_ckernel.SOURCE_KEY``); an edited ``_ckernel.c`` with
a stale build falls back to numba (whose cache is keyed by :mod:`.jit_cache`) until
``pip install`` is run again. ``LAYERWATCH_GCODE_KERNEL=numba`` forces the numba kernel.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from layerwatch.gcode.kernel_abi import N_FSTATS, N_PROBE, N_STATS

__all__ = ["KernelOutput", "run_kernel", "backend", "compiled_module", "source_key"]

_SOURCE = Path(__file__).resolve().parent / "_ckernel.c"


def source_key(path: Path = _SOURCE) -> str | None:
    """SHA-256 of the C kernel's source (what setup.py compiles in), None where it is absent."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def compiled_module(source: Path | None = None):
    """The compiled kernel module when it is built from ``source`` (default: the
    ``_ckernel.c`` beside this file, where present), else None."""
    if os.environ.get("LAYERWATCH_GCODE_KERNEL", "").lower() == "numba":
        return None
    try:
        from layerwatch.gcode import _ckernel  # built by setup.py; absent without a compiler
    except ImportError:
        return None
    key = source_key(source or _SOURCE)
    if key is not None and key != _ckernel.SOURCE_KEY:
        return None  # built from another version of _ckernel.c
    return _ckernel


_C = compiled_module()


def backend() -> str:
    """``"c"`` or ``"numba"``: which kernel :func:`run_kernel` runs."""
    return "c" if _C is not None else "numba"


class KernelOutput(NamedTuple):
    """What the kernel returns, segments column by column (C-contiguous, writeable).

    Attributes
    ----------
    start, end : (S, 2) float64
        Segment end points, physical mm.
    z : (S,) float64
        Nozzle Z, mm.
    e : (S,) float64
        Filament fed along the segment (M221 applied, volumetric E converted), mm.
    line : (S,) int64
        1-based source line.
    tool : (S,) uint8
        Active tool.
    travel_line : (T,) int64
        Lines of travel moves.
    cmt : (C, 2) int64
        Byte offset of each ``;`` comment that may be a tag, and its line.
    probe_state : (P, N_PROBE) float64
        Modal state at the start of each probed line.
    stats : (N_STATS,) int64
    fstats : (N_FSTATS,) float64
        Filament totals, mm.
    """

    start: np.ndarray
    end: np.ndarray
    z: np.ndarray
    e: np.ndarray
    line: np.ndarray
    tool: np.ndarray
    travel_line: np.ndarray
    cmt: np.ndarray
    probe_state: np.ndarray
    stats: np.ndarray
    fstats: np.ndarray


def _run_c(buf, probes, chord_tol, e_rel_init, e_area_init) -> KernelOutput:
    a, b, z, e, line, tool, travel, cmt, probe, stats, fs = _C.run(
        buf, probes, float(chord_tol), bool(e_rel_init), float(e_area_init))
    return KernelOutput(
        np.frombuffer(a, np.float64).reshape(-1, 2), np.frombuffer(b, np.float64).reshape(-1, 2),
        np.frombuffer(z, np.float64), np.frombuffer(e, np.float64), np.frombuffer(line, np.int64),
        np.frombuffer(tool, np.uint8), np.frombuffer(travel, np.int64), np.frombuffer(cmt, np.int64).reshape(-1, 2),
        np.frombuffer(probe, np.float64).reshape(-1, N_PROBE), np.frombuffer(stats, np.int64)[:N_STATS],
        np.frombuffer(fs, np.float64)[:N_FSTATS])


def _run_numba(buf, probes, chord_tol, e_rel_init, e_area_init) -> KernelOutput:
    # numba, imported here and only here: ~0.3 s to import and ~0.5 s to load the cached kernel,
    # which the compiled module spares `gcode info`
    from layerwatch.gcode import kernel

    segf, segi, travel, cmt, probe, stats, fs = kernel.run_kernel(
        np.frombuffer(buf, np.uint8), probes, chord_tol, e_rel_init, e_area_init)
    return KernelOutput(
        np.ascontiguousarray(segf[:, 0:2]), np.ascontiguousarray(segf[:, 2:4]), segf[:, 4].copy(),
        segf[:, 5].copy(), segi[:, 0].copy(), segi[:, 1].astype(np.uint8), travel, cmt, probe, stats, fs)


def run_kernel(buf, probes: np.ndarray, chord_tol: float, e_rel_init: bool = False,
               e_area_init: float = 0.0, *, use: str | None = None) -> KernelOutput:
    """Lex and execute G-code bytes ``buf`` (the arguments of :func:`layerwatch.gcode.kernel.run_kernel`).

    ``use`` picks ``"c"`` or ``"numba"`` (tests); default :func:`backend`.
    """
    probes = np.ascontiguousarray(probes, np.int64)
    use = use or backend()
    if use == "c":
        if _C is None:
            raise RuntimeError("the compiled G-code kernel is not built (pip install -e . builds it)")
        return _run_c(buf, probes, chord_tol, e_rel_init, e_area_init)
    return _run_numba(buf, probes, chord_tol, e_rel_init, e_area_init)
