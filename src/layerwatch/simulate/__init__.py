"""Virtual prints: camera-view photos of each layer with injected failures and ground truth.

See :mod:`layerwatch.simulate.camera_sim` for how the photos differ from the
reference renderer.
"""

from layerwatch.simulate.camera_sim import (
    PrintSimulator,
    SimFrame,
    save_frame,
    simulate_layer,
    simulate_print,
)
from layerwatch.simulate.failures import (
    EXTRA_TYPES,
    FAILURE_TYPES,
    SIMULATED_TYPES,
    Failure,
    Scenario,
    patch_layers,
    random_scenarios,
    thin_wall_segments,
)
from layerwatch.simulate.scene import default_camera, default_markers
from layerwatch.simulate.settings import SimSettings

__all__ = [
    "EXTRA_TYPES",
    "FAILURE_TYPES",
    "SIMULATED_TYPES",
    "Failure",
    "PrintSimulator",
    "Scenario",
    "SimFrame",
    "SimSettings",
    "default_camera",
    "default_markers",
    "patch_layers",
    "random_scenarios",
    "save_frame",
    "simulate_layer",
    "simulate_print",
    "thin_wall_segments",
]
