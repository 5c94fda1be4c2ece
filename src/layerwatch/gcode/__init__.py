"""layerwatch.gcode: read any slicer's G-code into per-layer toolpaths; insert snapshot blocks.

Public API
----------
read_toolpath(source, *, filament_diameter=None, progress=None) -> Toolpath
postprocess.insert_snapshots(data, snapshot, printer) -> bytes
"""

from layerwatch.gcode.reader import read_toolpath
from layerwatch.gcode.toolpath import FEATURES, Layer, Toolpath

__all__ = ["read_toolpath", "Toolpath", "Layer", "FEATURES"]
