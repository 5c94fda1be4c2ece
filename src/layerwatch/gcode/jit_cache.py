"""The kernel's on-disk compiled code, keyed on ALL its sources and on numba.

numba's ``cache=True`` re-validates a cached function against the timestamp
of its own source file only. The G-code kernel (:mod:`.kernel`) inlines the
lexer of :mod:`.lexer` and the arc routine of :mod:`.arcs`, so an edit to ``arcs.py`` (or a package upgrade
that changes it, or a new numba) would leave stale machine code in use.
:func:`ensure_fresh` runs when :mod:`.kernel` is imported, before anything is
compiled or loaded: it hashes the kernel's sources together with the numba,
Python and CPU versions and, when the hash differs from the stamp written
beside the cache, deletes the kernel's cache files so numba compiles afresh.

The cache lives in the package's ``__pycache__`` (numba's default when it is
writable); when it is not, numba falls back to its user-wide cache, which this
module does not manage (a read-only install keeps whatever its installer built).
"""

from __future__ import annotations

import hashlib
import platform
import sys
from collections.abc import Iterable
from pathlib import Path

import numba

__all__ = ["KERNEL_SOURCES", "cache_key", "ensure_fresh", "STAMP_NAME"]

_HERE = Path(__file__).resolve().parent
#: every source file whose code numba compiles into the kernel's cached functions
KERNEL_SOURCES: tuple[Path, ...] = tuple(_HERE / f for f in ("kernel.py", "kernel_abi.py", "lexer.py", "arcs.py"))
STAMP_NAME = "layerwatch-kernel.key"


def cache_key(sources: Iterable[Path], extra: Iterable[str] | None = None) -> str:
    """SHA-256 over the sources' bytes and the toolchain (numba, Python, CPU) versions."""
    h = hashlib.sha256()
    for path in sources:
        h.update(path.name.encode() + b"\0")
        h.update(path.read_bytes())
    tool = extra if extra is not None else (numba.__version__, sys.version, platform.machine())
    for part in tool:
        h.update(b"\0" + str(part).encode())
    return h.hexdigest()


def ensure_fresh(cache_dir: Path, module_stem: str, key: str) -> bool:
    """Delete ``module_stem``'s numba cache files in ``cache_dir`` unless its stamp says ``key``.

    Returns True when the cache was cleared (or had no stamp yet). Best effort: a
    read-only cache directory is left alone (numba then uses its own fallback).
    """
    stamp = cache_dir / STAMP_NAME
    try:
        if stamp.read_text() == key:
            return False
    except OSError:
        pass
    try:
        for f in list(cache_dir.glob(f"{module_stem}.*.nbi")) + list(cache_dir.glob(f"{module_stem}.*.nbc")):
            f.unlink(missing_ok=True)
        cache_dir.mkdir(exist_ok=True)
        stamp.write_text(key)
    except OSError:
        pass
    return True
