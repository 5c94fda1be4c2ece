"""Reference cache (render once, atomic entries) and parallel/Dask rendering of many layers."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from render_parts import square_part

from layerwatch.errors import MissingExtraError, RenderError
from layerwatch.render import backend
from layerwatch.render.backend import render_layers
from layerwatch.render.cache import ReferenceCache, file_hash, toolpath_hash
from layerwatch.render.fast import StackRenderer
from layerwatch.render.settings import RenderSettings


def _files(d):
    return sorted(p for p in d.rglob("*") if p.is_file())


def test_identical_parts_render_once(tmp_path, small_view, monkeypatch):
    calls = []
    real = backend.render_reference

    def counting(*a, **k):
        calls.append(a[1])
        return real(*a, **k)

    monkeypatch.setattr(backend, "render_reference", counting)
    cache = ReferenceCache(tmp_path)
    first = [backend.render_cached(cache, square_part(3, center=(5, -3)), i, small_view) for i in range(3)]
    # a second, separately built but identical part: no rendering at all
    again = [backend.render_cached(cache, square_part(3, center=(5, -3)), i, small_view) for i in range(3)]
    assert calls == [0, 1, 2]
    assert cache.hits == 3 and cache.misses == 3
    for a, b in zip(first, again, strict=True):
        assert np.array_equal(a.image, b.image) and np.array_equal(a.mask, b.mask)
        assert np.array_equal(a.height, b.height) and a.layer == b.layer and a.z == b.z
    assert not [p for p in _files(tmp_path) if p.name.startswith(".tmp")]


def test_key_depends_on_everything(part, small_view):
    s = RenderSettings()
    h = toolpath_hash(part)
    k = ReferenceCache.key(h, s, small_view, 1)
    assert k != ReferenceCache.key(h, s, small_view, 2)
    assert k != ReferenceCache.key(h, RenderSettings(light="directional"), small_view, 1)
    from layerwatch.geometry.topview import TopView

    assert k != ReferenceCache.key(h, s, TopView(7.0, 30, 30, (5, -3)), 1)
    assert k != ReferenceCache.key(toolpath_hash(square_part(4, center=(5, -2.9))), s, small_view, 1)
    assert k == ReferenceCache.key(toolpath_hash(square_part(4, center=(5, -3))), s, small_view, 1)


def test_failed_render_leaves_no_entry(tmp_path):
    cache = ReferenceCache(tmp_path)

    def boom():
        raise RenderError("blender crashed")

    with pytest.raises(RenderError):
        cache.get_or_render("ab" * 20, boom)
    assert _files(tmp_path) == []


def test_corrupt_entry_is_rendered_again(tmp_path, part, small_view):
    cache = ReferenceCache(tmp_path)
    r = backend.render_cached(cache, part, 0, small_view)
    (entry,) = _files(tmp_path)
    entry.write_bytes(b"garbage")
    cache2 = ReferenceCache(tmp_path)
    r2 = backend.render_cached(cache2, part, 0, small_view)
    assert cache2.misses == 1 and np.array_equal(r.image, r2.image)


def test_file_hash(tmp_path):
    p = tmp_path / "a.gcode"
    p.write_bytes(b"G1 X1 Y1 E1\n" * 1000)
    import hashlib

    assert file_hash(p, chunk=100) == hashlib.sha256(p.read_bytes()).hexdigest()


def test_parallel_equals_sequential(part, small_view, tmp_path):
    seq = {i: StackRenderer(part, small_view).render(i) for i in range(4)}
    done = []
    par = list(render_layers(part, small_view, workers=2, chunk=2, progress=lambda d, t: done.append((d, t))))
    assert sorted(r.layer for r in par) == [0, 1, 2, 3]
    for r in par:
        assert np.array_equal(r.image, seq[r.layer].image)
        assert np.array_equal(r.mask, seq[r.layer].mask)
    assert done[-1] == (4, 4)
    # with a cache: the second run renders nothing
    cache = ReferenceCache(tmp_path)
    list(render_layers(part, small_view, layers=[1, 3], cache=cache))
    again = list(render_layers(part, small_view, layers=[3, 1], cache=cache))
    assert cache.misses == 2 and cache.hits == 2
    assert {r.layer for r in again} == {1, 3}


@pytest.mark.skipif(importlib.util.find_spec("distributed") is not None, reason="dask is installed")
def test_dask_missing_is_one_line(part, small_view):
    with pytest.raises(MissingExtraError, match=r"layerwatch\[dask\]"):
        list(render_layers(part, small_view, scheduler="tcp://127.0.0.1:1"))
