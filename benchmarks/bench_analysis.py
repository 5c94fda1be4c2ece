"""Speed of one layer's analysis vs the naive baseline (skimage HOG + per-block scipy).

Run: ``python benchmarks/bench_analysis.py`` or ``pytest benchmarks/bench_analysis.py -s``.
Both paths use the same 600 x 600 top view (90 x 90 mm at 6.67 px/mm; a
hatched part with spaghetti beside it) in the same process, one thread.
Targets (issue 7): full analysis (HOG of both images, one measure, threshold,
regions) <= 30 ms; all twelve measures <= 100 ms; >= 50x the baseline.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "analysis"))

from analysis_scenes import part_scene  # noqa: E402

from layerwatch.analysis.scoring import analyze_layer  # noqa: E402
from layerwatch.analysis.settings import METRIC_NAMES, AnalysisSettings  # noqa: E402
from layerwatch.geometry.topview import TopView  # noqa: E402

TOPVIEW = TopView(px_per_mm=6.67, width_mm=90.0, height_mm=90.0, center_mm=(110.0, 100.0))


def _best(fn, repeat: int) -> float:
    """Best wall time of ``repeat`` calls, ms."""
    best = math.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def _naive_measure(name):
    """Per-block reference implementations (scipy calls, one block at a time)."""
    from scipy import stats
    from scipy.spatial import distance

    k = 36
    fns = {
        "cosine": lambda x, y: 1 - distance.cosine(x, y),
        "sqeuclidean": lambda x, y: 1 - distance.sqeuclidean(x, y) / 2,
        "euclidean": lambda x, y: 1 - distance.euclidean(x, y) / math.sqrt(2),
        "l1": lambda x, y: 1 - distance.cityblock(x, y) / math.sqrt(2 * k),
        "sorensen": lambda x, y: 1 - distance.braycurtis(x, y),
        "hellinger": lambda x, y: 1 - distance.euclidean(np.sqrt(x / x.sum()), np.sqrt(y / y.sum())) / math.sqrt(2),
        "clark": lambda x, y: 1 - math.sqrt(np.nansum(((x - y) / (x + y)) ** 2)) / math.sqrt(k),
        "jaccard": lambda x, y: np.dot(x, y) / (distance.sqeuclidean(x, y) + np.dot(x, y)),
        "dice": lambda x, y: 1 - distance.sqeuclidean(x, y) / (np.dot(x, x) + np.dot(y, y)),
        "pearson": lambda x, y: (stats.pearsonr(x, y).statistic + 1) / 2,
        "spearman": lambda x, y: (stats.spearmanr(x, y).statistic + 1) / 2,
        "kendall": lambda x, y: (stats.kendalltau(x, y).statistic + 1) / 2,
    }
    return fns[name]


def naive_analysis(top, ref, foot, metrics=("cosine",), threshold=0.7):
    """The baseline: skimage.feature.hog on both images, one scipy call per block, label."""
    import warnings

    from scipy import ndimage
    from skimage.feature import hog

    def blocks(img):
        h = hog(img, orientations=9, pixels_per_cell=(8, 8), cells_per_block=(2, 2), feature_vector=False)
        return h.reshape(h.shape[0], h.shape[1], -1)

    a, b = blocks(top), blocks(ref)
    n, m = a.shape[:2]
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # constant blocks: scipy warns and returns NaN
        for name in metrics:
            fn = _naive_measure(name)
            heat = np.empty((n, m))
            for i in range(n):
                for j in range(m):
                    try:
                        heat[i, j] = fn(a[i, j], b[i, j])
                    except ValueError:  # empty block: NaN that scipy refuses
                        heat[i, j] = np.nan
            heat = np.nan_to_num(heat, nan=1.0)
            labels, count = ndimage.label(heat < threshold)
            out[name] = (heat, ndimage.find_objects(labels), count)
    return out


def run(repeat: int = 25) -> dict[str, float]:
    ref, photo, foot = part_scene(0, "spaghetti", topview=TOPVIEW)
    assert photo.shape == (600, 600)
    settings = AnalysisSettings()
    analyze_layer(photo, ref, foot, TOPVIEW, settings, all_metrics=True)  # JIT warm-up
    ours_one = _best(lambda: analyze_layer(photo, ref, foot, TOPVIEW, settings), repeat)
    ours_all = _best(lambda: analyze_layer(photo, ref, foot, TOPVIEW, settings, all_metrics=True), repeat)
    res = analyze_layer(photo, ref, foot, TOPVIEW, settings)
    naive_one = _best(lambda: naive_analysis(photo, ref, foot), 3)
    naive_all = _best(lambda: naive_analysis(photo, ref, foot, METRIC_NAMES), 1)
    figures = {
        "ours_one_ms": ours_one,
        "ours_all12_ms": ours_all,
        "naive_one_ms": naive_one,
        "naive_all12_ms": naive_all,
        "ratio_one": naive_one / ours_one,
        "ratio_all12": naive_all / ours_all,
    }
    print(f"\n600x600 layer, one thread; stages of one run: {', '.join(f'{k} {v:.1f} ms' for k, v in res.timings_ms.items())}")
    print(f"full analysis, cosine:   ours {ours_one:7.1f} ms   naive {naive_one:8.1f} ms   ratio {figures['ratio_one']:6.1f}x  (target <= 30 ms, >= 50x)")
    print(f"full analysis, all 12:   ours {ours_all:7.1f} ms   naive {naive_all:8.1f} ms   ratio {figures['ratio_all12']:6.1f}x  (target <= 100 ms)")
    return figures


def test_bench_analysis():
    figures = run(repeat=5)
    assert all(np.isfinite(v) and v > 0 for v in figures.values())


if __name__ == "__main__":
    run()
