"""What a printer's job start derives from its camera model and its file alone, kept for its next job.

A job's pipeline starts by finding, ray by ray, where its camera's pixels meet the bed and the
print's prism: the scene channel's view maps (:class:`~layerwatch.pipeline.scene.SceneModel`: the
observed square, its box, the plane maps on the part's reach; every working pixel of the camera
undistorted) and the nothing-extruded check's box and plane maps
(:meth:`~layerwatch.pipeline.checks.JobChecks.maps`). With the example camera that is ~60 ms of a
job start's CPU, more than half a warm frame, and none of it depends on anything but the camera
model (intrinsics, distortion, image size, pose), the top view, the settings and the print's
reach and height.

A farm printer prints the same files again and again with the same camera: :class:`JobGeometry`
is one printer's memo of that work (the farm keeps one per printer, :data:`layerwatch.farm.remote.GEOMETRY`),
so its next job with the same inputs takes the arrays its last job made. Nothing is shared between
printers (a printer is never given another's geometry, even for the same file and camera).

Exactness: the kept arrays are made read-only (a job that wrote into them would raise, not
corrupt the next job), and a job's scene model is a copy of a model that never saw a photo, reset
for the job as the constructor resets it (:meth:`JobGeometry.scene`): a job built from the memo
holds the same values as one built afresh, bit for bit (tested; and over several jobs by
``benchmarks/farm_records.py --jobs``).
"""

from __future__ import annotations

import copy
import hashlib
import json
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from layerwatch.analysis.settings import SceneSettings
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.scene import SceneModel

__all__ = ["JobGeometry", "PrinterGeometries", "geometry_key"]

T = TypeVar("T")


def geometry_key(kind: str, camera: CameraModel, topview: TopView, **inputs: Any) -> str:
    """Hex key of a piece of job geometry: its kind, the camera model's exact values, the top view and ``inputs``.

    Parameters
    ----------
    kind : str
        What is kept (``"scene"``, ``"checks"``).
    camera : CameraModel
        Intrinsics, distortion, image size and pose are keyed by their exact bytes.
    topview : TopView
    **inputs
        The other inputs, JSON-serialisable (settings as ``model_dump(mode="json")``, the reach as floats).
    """
    blob = json.dumps(
        {
            "kind": kind,
            "topview": topview.to_dict(),
            "camera": {name: None if value is None else np.asarray(value, np.float64).tobytes().hex()
                       for name, value in (("K", camera.K), ("dist", camera.dist), ("size", camera.image_size),
                                           ("rvec", camera.rvec), ("tvec", camera.tvec))},
            "inputs": inputs,
        },
        sort_keys=True,
    )
    return hashlib.sha256(blob.encode()).hexdigest()


def _freeze(value: Any) -> None:
    """Make the arrays of ``value`` (an array, or a tuple/list of them, nested) read-only."""
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif isinstance(value, tuple | list):
        for v in value:
            _freeze(v)


class JobGeometry:
    """One printer's job geometry, by key; the last ``max_entries`` kinds x inputs kept (least recently used dropped).

    Thread-safe. ``hits`` and ``misses`` count the look-ups.

    Parameters
    ----------
    max_entries : int
        Entries kept (a scene model and the checks' maps per file and camera: 2 hold a printer's last file).
    """

    def __init__(self, max_entries: int = 2) -> None:
        if max_entries < 1:
            raise ValueError(f"max_entries must be >= 1, got {max_entries}")
        self.max_entries = int(max_entries)
        self._items: OrderedDict[str, Any] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def __len__(self) -> int:
        return len(self._items)

    def get(self, key: str, build: Callable[[], T]) -> T:
        """The value kept under ``key``, else ``build()`` (its arrays made read-only, then kept).

        ``build`` runs outside the lock; two callers that miss at once both build (the same value).
        """
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                self.hits += 1
                return self._items[key]
            self.misses += 1
        value = build()
        _freeze(value)
        with self._lock:
            self._items[key] = value
            self._items.move_to_end(key)
            while len(self._items) > self.max_entries:
                self._items.popitem(last=False)
        return value

    def scene(self, camera: CameraModel, topview: TopView, settings: SceneSettings, bed_photo: np.ndarray | None, *,
              reach_mm: tuple[float, float, float, float] | None, top_z_mm: float | None) -> SceneModel:
        """A new job's :class:`~layerwatch.pipeline.scene.SceneModel`, as ``SceneModel(camera, topview, settings,
        bed_photo, reach_mm=..., top_z_mm=...)`` builds it.

        The model kept for these inputs never sees a photo: the job gets a shallow copy of it (its
        view maps and masks read-only and shared; any list, dict or set copied) reset for the job
        (:meth:`SceneModel.reset <layerwatch.pipeline.scene.SceneModel.reset>`, what the constructor
        ends with), which creates every piece of per-job state anew.
        """
        reach = None if reach_mm is None else [float(v) for v in reach_mm]
        key = geometry_key("scene", camera, topview, settings=settings.model_dump(mode="json"), reach_mm=reach,
                           top_z_mm=None if top_z_mm is None else float(top_z_mm))

        def build() -> SceneModel:
            model = SceneModel(camera, topview, settings, None, reach_mm=reach_mm, top_z_mm=top_z_mm)
            for value in vars(model).values():
                _freeze(value)
            return model

        template = self.get(key, build)
        model = copy.copy(template)
        for name, value in vars(model).items():
            if isinstance(value, list | dict | set):
                setattr(model, name, copy.copy(value))
        model.reset(bed_photo)
        return model


class PrinterGeometries:
    """The :class:`JobGeometry` of each printer of a process, by printer name; the last ``max_printers`` used kept.

    Parameters
    ----------
    max_printers : int
        Printers whose geometry is kept (least recently used dropped). A kept printer holds the arrays
        its current job holds (shared, not copied) and, between its jobs, its last job's.
    """

    def __init__(self, max_printers: int = 1024) -> None:
        if max_printers < 1:
            raise ValueError(f"max_printers must be >= 1, got {max_printers}")
        self.max_printers = int(max_printers)
        self._printers: OrderedDict[str, JobGeometry] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._printers)

    def of(self, printer: str) -> JobGeometry:
        """``printer``'s geometry (a new, empty one the first time)."""
        with self._lock:
            geo = self._printers.get(printer)
            if geo is None:
                geo = self._printers[printer] = JobGeometry()
                while len(self._printers) > self.max_printers:
                    self._printers.popitem(last=False)
            else:
                self._printers.move_to_end(printer)
            return geo

    def clear(self) -> None:
        """Forget every printer's geometry."""
        with self._lock:
            self._printers.clear()
