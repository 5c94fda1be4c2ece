"""References shared between pipelines (``layerwatch.pipeline.shared_references``): the same references as rendering.

A pipeline that reads some layers from the store (another pipeline rendered them) and renders others itself
(its renderer catching up over the layers it skipped) must give, layer for layer, the reference a pipeline of its
own renders; pipelines whose camera model differs in any digit share nothing; what is stored is read-only and
its memory bounded.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from layerwatch.pipeline.shared_references import SharedReferences, reference_identity
from layerwatch.pipeline.step import LayerPipeline, Reference
from layerwatch.simulate import default_camera


@pytest.fixture(scope="module")
def job():
    from layerwatch.examples import PART_CONFIG, PART_GCODE
    from layerwatch.gcode import read_toolpath
    from layerwatch.pipeline.config import resolve_config

    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    return tp, default_camera(cfg.topview.topview(), image_size=(1280, 720)), cfg


def _same(a: Reference, b: Reference, what: str) -> None:
    np.testing.assert_array_equal(a.image, b.image, err_msg=what)
    np.testing.assert_array_equal(a.footprint, b.footprint, err_msg=what)
    assert a.z == b.z
    assert a.hog is not None and b.hog is not None
    for x, y in zip(a.hog, b.hog, strict=True):
        np.testing.assert_array_equal(x, y, err_msg=what)


def test_a_pipeline_that_reads_some_layers_and_renders_the_others_gives_its_own_references(job):
    tp, cam, cfg = job
    store = SharedReferences()
    first = LayerPipeline(tp, cam, cfg, memo=1, shared=store)
    second = LayerPipeline(tp, cam, cfg, memo=1, shared=store)
    alone = LayerPipeline(tp, cam, cfg, memo=1)
    renders: list[int] = []
    real = second.renderer.render
    second.renderer.render = lambda i, c=None: (renders.append(i), real(i, c))[1]  # type: ignore[method-assign]
    n = tp.n_layers
    for k in range(0, n, 3):  # the first printer renders every third layer, ahead of the second
        first.reference(k)
    for k in range(n):
        ref = second.reference(k)
        _same(ref, alone.reference(k), f"layer {k}")
        with pytest.raises(ValueError):  # a stored reference is not writeable
            ref.image[0, 0] = 1
        second.forget_references()
        alone.forget_references()
    # the second printer rendered only the layers the first had not: its renderer caught up over the others
    assert renders == [k for k in range(n) if k % 3]
    assert store.hits == len(range(0, n, 3))
    assert len(store) == n


def test_a_camera_model_that_differs_in_any_digit_shares_nothing(job):
    tp, cam, cfg = job
    moved = replace(cam, tvec=np.asarray(cam.tvec, np.float64) + 1e-9)
    store = SharedReferences()
    a, b = LayerPipeline(tp, cam, cfg, shared=store), LayerPipeline(tp, moved, cfg, shared=store)
    def key(p: LayerPipeline) -> str:
        return reference_identity(p.toolpath, p.camera, p.config, p.topview, p.match_camera)

    assert key(a) != key(b)
    assert key(a) == key(LayerPipeline(tp, cam, cfg))
    a.reference(0)
    b.reference(0)
    assert store.hits == 0 and len(store) == 2


def test_the_store_drops_the_least_recently_used_past_its_budget():
    def ref(value: int) -> Reference:
        img = np.full((512, 512), value, np.uint8)  # 0.25 MB, with the footprint 0.5 MB
        return Reference(img, np.zeros(img.shape, bool), 0.2, (np.zeros(4, np.float32),))

    store = SharedReferences(max_mb=1.2)
    for k in range(3):
        store.put("a", k, ref(k))
    assert store.get("a", 0) is None  # 3 x 0.5 MB > 1.2 MB: the oldest went
    assert store.get("a", 1) is not None  # now the most recently used
    store.put("a", 3, ref(3))
    assert store.get("a", 2) is None and store.get("a", 1) is not None and store.get("a", 3) is not None
    assert store.nbytes <= store.max_bytes
    with pytest.raises(ValueError):
        SharedReferences(max_mb=0)
