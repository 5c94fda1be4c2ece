"""The kernel's compiled cache is invalidated by a change to ANY kernel source or to numba."""

from __future__ import annotations

from pathlib import Path

import numba

from layerwatch.gcode import jit_cache
from layerwatch.gcode import kernel as K


def _fake_cache(d: Path) -> list[Path]:
    d.mkdir(exist_ok=True)
    files = [d / "kernel.run_kernel-100.py311.nbi", d / "kernel.run_kernel-100.py311.1.nbc", d / "arcs.f-1.py311.nbi"]
    for f in files:
        f.write_bytes(b"x")
    return files


def test_a_change_to_any_source_or_to_numba_clears_the_kernel_cache(tmp_path):
    a, b = tmp_path / "kernel.py", tmp_path / "arcs.py"
    a.write_text("k = 1\n")
    b.write_text("r = 1\n")
    cache = tmp_path / "__pycache__"
    nbi, nbc, other = _fake_cache(cache)
    key = jit_cache.cache_key((a, b), ("0.60", "3.11"))
    assert jit_cache.ensure_fresh(cache, "kernel", key)  # no stamp yet: cleared
    assert not nbi.exists() and not nbc.exists() and other.exists()
    nbi, nbc, other = _fake_cache(cache)
    assert not jit_cache.ensure_fresh(cache, "kernel", key)  # same sources: kept
    assert nbi.exists() and nbc.exists()
    b.write_text("r = 2\n")  # the inlined arc routine changed
    key2 = jit_cache.cache_key((a, b), ("0.60", "3.11"))
    assert key2 != key and jit_cache.ensure_fresh(cache, "kernel", key2)
    assert not nbi.exists() and not nbc.exists()
    assert jit_cache.cache_key((a, b), ("0.61", "3.11")) != key2  # a numba upgrade changes the key


def test_kernel_key_covers_the_arc_source_and_numba():
    names = {p.name for p in jit_cache.KERNEL_SOURCES}
    assert {"kernel.py", "kernel_abi.py", "lexer.py", "arcs.py"} <= names
    assert K.arc_geometry.py_func.__code__.co_filename.endswith("arcs.py")
    key = jit_cache.cache_key(jit_cache.KERNEL_SOURCES)
    assert key != jit_cache.cache_key(jit_cache.KERNEL_SOURCES, ("not-" + numba.__version__,))
    stamp = Path(K.__file__).resolve().parent / "__pycache__" / jit_cache.STAMP_NAME
    if stamp.parent.is_dir() and stamp.exists():  # importing the kernel stamped its cache with this key
        assert stamp.read_text() == key
