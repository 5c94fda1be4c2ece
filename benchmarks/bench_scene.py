"""Cost of the scene channel per layer on a 1080p frame, against the per-layer step without it.

Run: ``python benchmarks/bench_scene.py``. One process, one thread: a
simulated print of the example part photographed at 1920 x 1080, the same
photos analysed by :meth:`LayerPipeline.process` with the recommended
settings, once with ``[scene] enabled = false`` (the baseline: warp,
reference from the memo, HOG comparison) and once with it on (plus the
scene model: working image, projection of the layer, photometric fit,
change blocks, top-view regions, update of the expected appearance).
References are rendered before the timing (cached, as in a monitored job).
Prints the median per-layer times, the scene channel's own median and the ratio.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from layerwatch.examples import PART_CONFIG, PART_GCODE  # noqa: E402
from layerwatch.gcode import read_toolpath  # noqa: E402
from layerwatch.pipeline.config import recommended_config  # noqa: E402
from layerwatch.pipeline.step import LayerPipeline  # noqa: E402
from layerwatch.simulate import PrintSimulator, default_camera  # noqa: E402

cv2.setNumThreads(1)
LAYERS = range(2, 14)


def _run(pipe: LayerPipeline, photos: dict[int, np.ndarray], bed: np.ndarray) -> tuple[list[float], list[float]]:
    pipe.new_print(bed)
    totals, scene = [], []
    for i, photo in photos.items():
        t = time.perf_counter()
        res = pipe.process(photo, i)
        totals.append((time.perf_counter() - t) * 1e3)
        assert res.status == "ok", res.message
        scene.append(res.timings_ms.get("scene", 0.0))
    return totals, scene


def main() -> dict[str, float]:
    tp = read_toolpath(PART_GCODE)
    cfg_on = recommended_config(PART_CONFIG)
    cfg_off = cfg_on.model_copy(update={"scene": cfg_on.scene.model_copy(update={"enabled": False})})
    tv = cfg_on.topview.topview()
    cam = default_camera(tv, image_size=(1920, 1080))
    sim = PrintSimulator(tp, cam, tv, (), seed=7)
    bed = sim.bed_photo()
    photos = {i: sim.frame(i).photo for i in LAYERS}
    off = LayerPipeline(tp, cam, cfg_off, memo=tp.n_layers)
    on = LayerPipeline(tp, cam, cfg_on, memo=tp.n_layers, bed_photo=bed)
    for p in (off, on):
        p.prepare(range(0, max(LAYERS) + 1))
        p.process(photos[LAYERS[0]], LAYERS[0])  # warm the warp tables and kernels
    rounds = [(_run(off, photos, bed), _run(on, photos, bed)) for _ in range(2)]
    base = float(np.median([t for (b, _), _ in rounds for t in b]))
    with_scene = float(np.median([t for _, (w, _) in rounds for t in w]))
    scene = float(np.median([t for _, (_, s) in rounds for t in s]))
    print(f"per-layer step, 1920x1080, {len(LAYERS)} layers x 2 rounds, one thread")
    print(f"  without the scene channel (baseline): {base:7.1f} ms")
    print(f"  with the scene channel:               {with_scene:7.1f} ms  (ratio {with_scene / base:.2f}x)")
    print(f"  the scene channel itself:             {scene:7.1f} ms")
    return {"base_ms": base, "scene_on_ms": with_scene, "scene_ms": scene}


if __name__ == "__main__":
    main()
