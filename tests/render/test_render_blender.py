"""Blender Cycles backend: one small layer when `blender` is installed; clean errors otherwise."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from render_parts import square_part

from layerwatch.errors import RenderError
from layerwatch.geometry.topview import TopView
from layerwatch.render.backend import render_cached
from layerwatch.render.blender import MissingBlenderError, bead_mesh, render_layer_blender
from layerwatch.render.cache import ReferenceCache
from layerwatch.render.settings import RenderSettings

HAS_BLENDER = shutil.which("blender") is not None
TV = TopView(6.67, 22.5, 22.5, (0.0, 0.0))  # 150 x 150 px


def test_bead_mesh_is_closed():
    v, loops, sizes = bead_mesh(np.array([[0.0, 0], [1, 1]]), np.array([[2.0, 0], [1, 1]]),
                                np.array([0.3, 0.3]), np.array([0.45, 0.45]), np.array([0.3, 0.3]))
    import trimesh

    faces, start = [], 0
    for n in sizes:
        f = loops[start : start + n]
        faces += [[f[0], f[i], f[i + 1]] for i in range(1, n - 1)]
        start += n
    mesh = trimesh.Trimesh(v, np.array(faces), process=True)
    assert len(mesh.split(only_watertight=False)) == 2
    assert all(m.is_watertight for m in mesh.split(only_watertight=False))
    assert v[:, 2].max() == pytest.approx(0.3) and v[:, 2].min() == pytest.approx(0.0)


def test_missing_blender_one_line():
    with pytest.raises(MissingBlenderError, match="apt-get install blender"):
        render_layer_blender(square_part(1), 0, TV, executable="no-such-blender-xyz")


@pytest.mark.blender
@pytest.mark.skipif(not HAS_BLENDER, reason="blender executable not on PATH (apt-get install blender)")
def test_blender_renders_small_layer():
    part = square_part(2, size=12.0)
    r = render_layer_blender(part, 1, TV, RenderSettings(blender_samples=4))
    assert r.image.shape == TV.shape and r.image.dtype == np.uint8
    inside = r.mask
    assert inside.sum() > 1000
    assert r.image[inside].mean() > r.image[~inside].mean() + 40  # plastic lit, bed dark


@pytest.mark.blender
@pytest.mark.skipif(not HAS_BLENDER, reason="blender executable not on PATH (apt-get install blender)")
def test_blender_timeout_leaves_no_cache_entry(tmp_path):
    part = square_part(1, size=12.0)
    cache = ReferenceCache(tmp_path)
    s = RenderSettings(backend="blender", blender_samples=4, blender_timeout_s=0.05)
    with pytest.raises(RenderError, match="did not finish"):
        render_cached(cache, part, 0, TV, s)
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]
