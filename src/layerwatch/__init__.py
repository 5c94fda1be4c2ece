"""layerwatch: layer-wise 3D printing anomaly detection.

Implements and extends Petsiuk & Pearce, "Open Source in-Situ Layer-wise 3D
Printing Image Anomaly Detection Using Histograms of Oriented Gradients and a
Physics-Based Rendering Engine" (Additive Manufacturing, 2022).

Every pipeline stage is a plain function over NumPy arrays and small
dataclasses; see ``layerwatch.gcode``, ``layerwatch.geometry``,
``layerwatch.render``, ``layerwatch.analysis`` and ``layerwatch.monitor``.
"""

from layerwatch.errors import LayerwatchError

__all__ = ["LayerwatchError", "__version__"]
__version__ = "0.1.0"
