"""layerwatch.render: reference images and footprint masks of G-code layers.

Modules (import what you need; nothing heavy is imported here):

* :mod:`~layerwatch.render.fast` — ``render_layer(toolpath, index, topview, settings)``
  -> :class:`~layerwatch.render.fast.Rendered` (image uint8, height float32 mm, mask bool);
  ``StackRenderer`` / ``render_stack`` for layer-by-layer work.
* :mod:`~layerwatch.render.mask` — ``gcode_mask(toolpath, index, topview, *, solid=False)``,
  ``stl_mask(mesh_or_path, z, topview, *, offset_mm=(0, 0, 0))``.
* :mod:`~layerwatch.render.cache` — ``ReferenceCache(dir)`` (render once, reuse).
* :mod:`~layerwatch.render.backend` — ``render_reference`` (fast or Blender) and
  ``render_layers`` (process pool or Dask).
* :mod:`~layerwatch.render.blender` — Blender Cycles through the ``blender`` executable.
"""
