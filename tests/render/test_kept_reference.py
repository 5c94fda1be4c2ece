"""The highest layer's reference kept past the memo (``LayerPipeline.reference``): the same reference as a render.

A farm pipeline memoises one reference and forgets it once the layer is recorded; the monitor's lag check then
asks for layer ``k - 1`` right after layer ``k``. The pipeline answers it from the image and footprint it kept
instead of resetting its renderer and rendering ``0 .. k - 1`` again; these tests hold that answer against a
render of that layer by a new pipeline (from the first layer, as the reset did), on the example part and real
slicers' files, with a skipped layer and a restart from the first layer.
"""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.step import LayerPipeline, Reference
from layerwatch.simulate import default_camera


def _job(source: str, shared_data):
    from layerwatch.examples import PART_CONFIG, PART_GCODE
    from layerwatch.gcode import read_toolpath
    from layerwatch.pipeline.config import resolve_config

    if source == "example":
        tp = read_toolpath(PART_GCODE)
        cfg = resolve_config(PART_CONFIG).config
    else:
        tp = read_toolpath((shared_data / "gcode" / source).read_bytes())
        x0, y0, x1, y1 = tp.bounds
        cfg = JobConfig(topview={"center_mm": ((x0 + x1) / 2, (y0 + y1) / 2), "width_mm": max(150.0, x1 - x0 + 30),
                                 "height_mm": max(150.0, y1 - y0 + 30), "px_per_mm": 3.0})
    cam = default_camera(cfg.topview.topview(), image_size=(1280, 720))
    return tp, cam, cfg


def _same(a: Reference, b: Reference, what: str) -> None:
    np.testing.assert_array_equal(a.image, b.image, err_msg=what)
    np.testing.assert_array_equal(a.footprint, b.footprint, err_msg=what)
    assert a.footprint.dtype == b.footprint.dtype == bool
    assert a.z == b.z
    assert a.hog is not None and b.hog is not None
    for x, y in zip(a.hog, b.hog, strict=True):
        np.testing.assert_array_equal(x, y, err_msg=what)


def _lag_checked(source: str, shared_data, layers: list[int], every: int = 1) -> int:
    """Run ``layers`` as a farm printer does (render, lag check's ``k - 1``, forget); compare; count kept hits."""
    tp, cam, cfg = _job(source, shared_data)
    pipe = LayerPipeline(tp, cam, cfg, memo=1)
    renders = []
    real = pipe.renderer.render
    pipe.renderer.render = lambda i, c=None: (renders.append(i), real(i, c))[1]  # type: ignore[method-assign]
    hits = 0
    for n, k in enumerate(layers):
        own = pipe.reference(k)
        pipe._keep(k, own)  # as process() does with the photo's layer
        if n % every == 0:
            _same(own, LayerPipeline(tp, cam, cfg, memo=1).reference(k), f"{source} layer {k}")
        if k >= 1:
            before = len(renders)
            prev = pipe.reference(k - 1)  # the lag check, right after layer k
            kept = len(renders) == before
            hits += kept
            if n % every == 0 or kept:
                _same(prev, LayerPipeline(tp, cam, cfg, memo=1).reference(k - 1), f"{source} layer {k - 1} after {k}")
        pipe.forget_references()  # the layer is recorded (a farm printer)
    return hits


def test_the_lag_checks_previous_layer_is_the_rendered_one_on_the_example_part(shared_data):
    tp, _, _ = _job("example", shared_data)
    n = tp.n_layers
    # in order, a skipped layer (the monitor missed a frame), then a restart from the first layer
    layers = [*range(0, 12), *range(13, n), 0, 1, 2, 3]
    hits = _lag_checked("example", shared_data, layers)
    # kept: k - 1 analysed on the photo before (not after the skip, where 12 was never analysed, nor at the restart)
    assert hits == sum(1 for a, b in zip(layers, layers[1:], strict=False) if b == a + 1) == n


@pytest.mark.slow
@pytest.mark.parametrize("source", ["prusaslicer-2.8.1_mini-cube_ascii.gcode", "cura-4.10.0_m83_multi-object.gcode",
                                    "miraclegrue_20mm-box.gcode"])
def test_the_lag_checks_previous_layer_is_the_rendered_one_on_slicers_files(source, shared_data):
    tp, _, _ = _job(source, shared_data)
    n = min(tp.n_layers, 40)
    layers = [*range(0, n // 2), *range(n // 2 + 1, n), 0, 1]
    assert _lag_checked(source, shared_data, layers, every=5) == n - 2
