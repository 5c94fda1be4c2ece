"""Simulated camera photos for the farm's ``camera = "sim"`` printers, shared between identical ones.

Printers that print the same G-code with the same injected failure, onset and
seed see the same simulated photos; :class:`SimFrames` renders each such
print once (its simulator is incremental, so layers are rendered in order
under a lock) and keeps the recent frames, so twenty virtual printers of one
part cost one simulation.
"""

from __future__ import annotations

import dataclasses
import hashlib
import threading
from collections import OrderedDict

import numpy as np

from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.pose import locate_bed
from layerwatch.pipeline.config import JobConfig
from layerwatch.simulate import Failure, PrintSimulator, default_camera

__all__ = ["SimFrames", "SimPrint"]


class SimPrint:
    """One simulated print: photos by layer (recent ones kept) and the camera located from its first photo.

    Parameters
    ----------
    toolpath : Toolpath
    config : JobConfig
        Top view and markers.
    failure : str or None
        Injected failure type.
    onset : int
        First failed layer.
    seed : int
    keep : int
        Frames kept in memory.
    """

    def __init__(self, toolpath: Toolpath, config: JobConfig, failure: str | None, onset: int, seed: int,
                 keep: int = 6) -> None:
        tv = config.topview.topview()
        truth = default_camera(tv)
        fails = [Failure(failure, onset=onset, seed=seed)] if failure else []
        self.n_layers = toolpath.n_layers
        self._sim = PrintSimulator(toolpath, truth, tv, fails, seed=seed)
        self._lock = threading.Lock()
        self._frames: OrderedDict[int, np.ndarray] = OrderedDict()
        self._keep = max(1, int(keep))
        #: the simulated camera with the pose found from the first photo's bed markers (as a user calibrates)
        self.located: CameraModel = locate_bed(dataclasses.replace(truth, rvec=None, tvec=None), self.frame(0),
                                               config.markers, tv)

    def frame(self, layer: int) -> np.ndarray:
        """The photo after ``layer`` (clamped to the last layer), BGR uint8 (H, W, 3); read-only."""
        i = min(max(int(layer), 0), self.n_layers - 1)
        with self._lock:
            hit = self._frames.get(i)
            if hit is None:
                hit = self._sim.frame(i).photo
                hit.setflags(write=False)
                self._frames[i] = hit
                while len(self._frames) > self._keep:
                    self._frames.popitem(last=False)
            else:
                self._frames.move_to_end(i)
            return hit


class SimFrames:
    """The farm's simulated prints, one per distinct (G-code, failure, onset, seed)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._prints: dict[tuple, SimPrint] = {}
        self._making: dict[tuple, threading.Lock] = {}

    def get(self, gcode: bytes, toolpath: Toolpath, config: JobConfig, failure: str | None, onset: int,
            seed: int) -> SimPrint:
        """The shared :class:`SimPrint` of these parameters (built on first use)."""
        key = (hashlib.sha256(gcode).hexdigest(), config.topview.model_dump_json(), failure,
               onset if failure else 0, seed)
        with self._lock:
            if key in self._prints:
                return self._prints[key]
            making = self._making.setdefault(key, threading.Lock())
        with making:  # one printer builds it; identical ones wait for that
            with self._lock:
                if key in self._prints:
                    return self._prints[key]
            made = SimPrint(toolpath, config, failure, onset, seed)
            with self._lock:
                self._prints[key] = made
            return made
