"""One entry point for a reference, whatever the backend; and many layers in parallel.

:func:`render_layers` renders a set of layers of one job: chunks of
consecutive layers go to worker processes (each keeps an incremental
height map for its chunk), or to a Dask cluster when a scheduler address is
given. Results come back as they finish, so memory holds only the chunks in
flight; a :class:`~layerwatch.render.cache.ReferenceCache` skips layers
already rendered.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed

from layerwatch.errors import require
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.topview import TopView
from layerwatch.render.cache import ReferenceCache, toolpath_hash
from layerwatch.render.fast import Rendered, StackRenderer, render_layer
from layerwatch.render.settings import RenderSettings

__all__ = ["render_cached", "render_reference", "render_layers"]


def render_reference(
    toolpath: Toolpath, index: int, topview: TopView, settings: RenderSettings | None = None
) -> Rendered:
    """Reference of layer ``index`` with the backend named in ``settings.backend``."""
    settings = settings or RenderSettings()
    if settings.backend == "blender":
        # optional backend (drives the blender executable): loaded only when asked for
        from layerwatch.render.blender import render_layer_blender

        return render_layer_blender(toolpath, index, topview, settings)
    return render_layer(toolpath, index, topview, settings)


def _render_chunk(toolpath: Toolpath, topview: TopView, settings: RenderSettings, layers: list[int]):
    """Worker: render consecutive layers, one height map for the chunk."""
    if settings.backend == "blender":
        # optional backend (drives the blender executable): loaded only when asked for
        from layerwatch.render.blender import render_layer_blender

        return [render_layer_blender(toolpath, i, topview, settings) for i in layers]
    sr = StackRenderer(toolpath, topview, settings)
    return [sr.render(i) for i in layers]


def _chunks(layers: list[int], size: int) -> list[list[int]]:
    return [layers[i : i + size] for i in range(0, len(layers), size)]


def render_cached(
    cache: ReferenceCache,
    toolpath: Toolpath,
    index: int,
    topview: TopView,
    settings: RenderSettings | None = None,
    gcode_hash: str | None = None,
) -> Rendered:
    """:func:`render_reference` of one layer through ``cache`` (rendered once per identical part and settings)."""
    settings = settings or RenderSettings()
    gh = gcode_hash or toolpath_hash(toolpath)
    key = cache.key(gh, settings, topview, index % max(toolpath.n_layers, 1))
    return cache.get_or_render(key, lambda: render_reference(toolpath, index, topview, settings))


def render_layers(
    toolpath: Toolpath,
    topview: TopView,
    settings: RenderSettings | None = None,
    layers: Iterable[int] | None = None,
    *,
    workers: int | None = 1,
    scheduler: str | None = None,
    cache=None,
    gcode_hash: str | None = None,
    chunk: int = 8,
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[Rendered]:
    """Render many layers, in parallel when asked; yields results as they finish.

    Parameters
    ----------
    toolpath, topview, settings
        As for :func:`render_reference`.
    layers : iterable of int, optional
        Layer indices; all layers when omitted.
    workers : int or None
        Worker processes; ``1`` renders in this process (incrementally),
        ``None`` uses every core.
    scheduler : str, optional
        Dask scheduler address (``"tcp://host:8786"``), or ``"local"`` for a
        local cluster; needs the ``dask`` extra.
    cache : ReferenceCache, optional
        Layers found there are not rendered again; new ones are stored.
    gcode_hash : str, optional
        Cache key of the G-code (default: hash of the toolpath arrays).
    chunk : int
        Consecutive layers per task.
    progress : callable(done, total), optional

    Yields
    ------
    Rendered
        One per layer, in completion order (``.layer`` says which).
    """
    settings = settings or RenderSettings()
    n = toolpath.n_layers
    todo = sorted({int(i) % n for i in (range(n) if layers is None else layers)}) if n else []
    total, done = len(todo), 0
    keys: dict[int, str] = {}
    if cache is not None:
        gh = gcode_hash or toolpath_hash(toolpath)
        missing = []
        for i in todo:
            keys[i] = cache.key(gh, settings, topview, i)
            hit = cache.get(keys[i])
            if hit is None:
                missing.append(i)
                continue
            cache.hits += 1
            done += 1
            if progress:
                progress(done, total)
            yield hit
        todo = missing
    for batch in _render_batches(toolpath, topview, settings, todo, workers, scheduler, chunk):
        for r in batch:
            if cache is not None:
                cache.misses += 1
                cache.put(keys[r.layer], r)
            done += 1
            if progress:
                progress(done, total)
            yield r


def _render_batches(toolpath: Toolpath, topview: TopView, settings: RenderSettings, todo: list[int],
                    workers: int | None, scheduler: str | None, chunk: int) -> Iterator[list[Rendered]]:
    """Render the layers ``todo``: on a Dask cluster, in worker processes, or here; lists in completion order."""
    if not todo:
        return
    if scheduler is not None:
        yield from _dask_map(toolpath, topview, settings, _chunks(todo, chunk), scheduler)
        return
    nw = (os.cpu_count() or 1) if workers is None else max(1, int(workers))
    if nw == 1 or len(todo) <= chunk:
        sr = StackRenderer(toolpath, topview, settings) if settings.backend == "fast" else None
        for i in todo:
            yield [sr.render(i) if sr is not None else render_reference(toolpath, i, topview, settings)]
        return
    size = max(1, min(chunk, -(-len(todo) // nw)))
    with ProcessPoolExecutor(max_workers=nw) as ex:
        futs = [ex.submit(_render_chunk, toolpath, topview, settings, c) for c in _chunks(todo, size)]
        for f in as_completed(futs):
            yield f.result()


def _dask_map(toolpath, topview, settings, chunks, scheduler: str):
    """Yield chunk results computed on a Dask cluster (lazy import)."""
    distributed = require("distributed", "dask", "rendering on a Dask cluster")
    if scheduler == "local":
        client = distributed.Client(distributed.LocalCluster(processes=True))
    else:
        client = distributed.Client(scheduler)
    try:
        tp = client.scatter(toolpath, broadcast=True)
        futs = [client.submit(_render_chunk, tp, topview, settings, c, pure=False) for c in chunks]
        for f in distributed.as_completed(futs):
            yield f.result()
    finally:
        client.close()
