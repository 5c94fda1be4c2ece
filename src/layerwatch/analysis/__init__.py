"""layerwatch.analysis: HOG block descriptors, the twelve similarity measures, scoring, pictures.

Modules (imported on demand; ``hog`` and ``metrics`` compile Numba kernels):

- :mod:`~layerwatch.analysis.hog` -- ``hog_blocks(image, cell_px=8, block_cells=2, bins=9,
  block_norm="L2-Hys", gamma=False) -> (N, M, k)``, skimage-exact.
- :mod:`~layerwatch.analysis.metrics` -- ``similarity(a, b, metric) -> (N, M) float32``,
  ``similarity_all``; names in ``METRIC_NAMES``.
- :mod:`~layerwatch.analysis.scoring` -- ``analyze_layer(top, reference, footprint, topview,
  settings, *, valid=None, layer=0, z=0.0) -> LayerResult``; ``block_geometry``.
- :mod:`~layerwatch.analysis.overlay` -- ``overlay_image``, ``heatmap_image``, ``write_overlay``.
- :mod:`~layerwatch.analysis.result` -- ``LayerResult``, ``Region``.
"""

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.analysis.settings import METRIC_NAMES, AnalysisSettings

__all__ = ["LayerResult", "Region", "AnalysisSettings", "METRIC_NAMES"]
