"""Per-layer latency of the whole pipeline on a 1920x1080 photo vs a naive same-process baseline.

Run: ``python benchmarks/bench_pipeline.py`` or ``pytest benchmarks/bench_pipeline.py -s``.

* ours: :meth:`layerwatch.pipeline.step.LayerPipeline.process` (cached
  per-Z warp tables, incremental reference renderer, Numba HOG, vectorised
  similarity over all blocks), a new layer (new Z) every call. Measured twice:
  with references rendered ahead (``prepare``, as the monitor does while the
  layer prints) and "cold" (rendering inside the call).
* baseline: ``cv2.undistort`` of the full photo + ``cv2.warpPerspective``
  with ``top_from_image``, ``skimage.feature.hog`` of both images and
  ``scipy.spatial.distance.cosine`` block by block in a Python loop, on the
  same (pre-rendered) references.

Both are checked to give nearly the same a% (correctness, not timing).
"""

from __future__ import annotations

import time

import numpy as np

from layerwatch.geometry.homography import top_from_image
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import default_camera, simulate_print
from layerwatch.simulate.parts import box_part


def _baseline(photo, ref, cam, tv, z, cfg) -> float:
    import cv2
    from scipy.spatial.distance import cosine
    from skimage.feature import hog

    st = cfg.analysis
    und = cv2.undistort(photo, cam.K, cam.dist)
    top = cv2.warpPerspective(und, top_from_image(cam, tv, z), (tv.shape[1], tv.shape[0]), flags=cv2.INTER_LINEAR)
    top = top.mean(axis=2)
    kw = {"orientations": st.bins, "pixels_per_cell": (st.cell_px, st.cell_px),
          "cells_per_block": (st.block_cells, st.block_cells), "block_norm": "L2-Hys", "feature_vector": False}
    ht, hr = hog(top, **kw), hog(ref.image.astype(float), **kw)
    n, m = ht.shape[:2]
    anom = 0
    c, b = st.cell_px, st.block_cells
    foot = ref.footprint
    for i in range(n):
        for j in range(m):
            if not foot[i * c : i * c + b * c, j * c : j * c + b * c].any():
                continue
            a, r = ht[i, j].ravel(), hr[i, j].ravel()
            s = 1.0 - cosine(a, r) if a.any() and r.any() else (1.0 if not a.any() and not r.any() else 0.0)
            anom += s < st.threshold
    return anom * (c / tv.px_per_mm) ** 2 / (foot.sum() / tv.px_per_mm**2)


def run(layers: int = 12, baseline_layers: int = 3) -> dict[str, float]:
    import cv2

    cv2.setNumThreads(1)
    cfg = JobConfig(analysis={"footprint_margin_mm": 0.0})
    tv = cfg.topview.topview()
    cam = default_camera(tv, image_size=(1920, 1080))
    tp = box_part(size_mm=30.0, height_mm=0.3 * (layers + 2), layer_h=0.3)
    frames = list(simulate_print(tp, cam, tv, (), seed=0, layers=range(1, layers + 1)))
    warm = LayerPipeline(tp, cam, cfg)
    warm.process(frames[0].photo, 0)  # JIT compile, lookup tables
    cold = LayerPipeline(tp, cam, cfg)
    cold.warper = warm.warper  # the one-off distortion lookup is per camera, not per layer
    cold_t = []
    for fr in frames:
        t = time.perf_counter()
        cold.process(fr.photo, fr.layer)
        cold_t.append(time.perf_counter() - t)
    hot = LayerPipeline(tp, cam, cfg, memo=layers + 2)
    hot.warper = warm.warper
    hot.prepare(range(1, layers + 1))
    hot_t, ours_a = [], []
    for fr in frames:
        t = time.perf_counter()
        res = hot.process(fr.photo, fr.layer)
        hot_t.append(time.perf_counter() - t)
        ours_a.append(res.anomaly_ratio)
    base_t, base_a = [], []
    for fr in frames[:baseline_layers]:
        ref = hot.reference(fr.layer)
        t = time.perf_counter()
        base_a.append(_baseline(fr.photo, ref, cam, tv, ref.z, cfg))
        base_t.append(time.perf_counter() - t)
    ours = float(np.median(hot_t)) * 1e3
    base = float(np.median(base_t)) * 1e3
    return {"ours_ms": ours, "cold_ms": float(np.median(cold_t)) * 1e3, "baseline_ms": base, "ratio": base / ours,
            "a_ours": float(np.mean(ours_a[:baseline_layers])), "a_base": float(np.mean(base_a))}


def report(r: dict[str, float]) -> None:
    print(f"pipeline, 1920x1080 photo -> 600x600 top view, new layer each call: {r['ours_ms']:.1f} ms/layer "
          f"(references prepared), {r['cold_ms']:.1f} ms/layer rendering inside the call")
    print(f"baseline undistort + warpPerspective + skimage hog + per-block scipy cosine: {r['baseline_ms']:.1f} ms/layer")
    print(f"speed-up vs baseline: {r['ratio']:.1f}x; a% ours {100 * r['a_ours']:.1f} % vs baseline {100 * r['a_base']:.1f} %")


def test_bench_pipeline():
    r = run(layers=6, baseline_layers=2)
    report(r)
    assert abs(r["a_ours"] - r["a_base"]) < 0.1  # same analysis (correctness, not timing)


if __name__ == "__main__":
    report(run())
