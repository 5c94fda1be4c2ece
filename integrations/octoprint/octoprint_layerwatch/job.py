"""One watched print: the job's G-code and camera -> layerwatch's per-layer step -> pause through OctoPrint.

:class:`JobWatch` is built when a print of a local file starts. On its worker
it reads the file (OctoPrint's file manager gives the path), checks that it
carries layerwatch's snapshot triggers, resolves the settings, loads the
camera model (locating the bed in ``bed_photo`` when the model has no pose)
and builds :class:`layerwatch.pipeline.step.LayerPipeline`. Each trigger then
goes through :class:`layerwatch.monitor.service.Monitor` (photo, analysis on its
own worker thread, :class:`~layerwatch.pipeline.policy.PausePolicy`, pause or
cancel through OctoPrint, alerts to the job file's ``[notify]`` targets), exactly
as ``layerwatch monitor`` does; the latest
result and its overlay go to the plugin's tab.

This module does not import OctoPrint: the host's pause/cancel and the
snapshot source are callables.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from layerwatch.analysis.overlay import overlay_image
from layerwatch.analysis.result import LayerResult
from layerwatch.errors import CameraError, LayerwatchError
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.pose import locate_bed
from layerwatch.monitor.cameras import Camera, decode_image, open_camera
from layerwatch.monitor.notify import Notifier
from layerwatch.monitor.printers.base import SnapshotTrigger
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline

from .options import job_config

__all__ = ["JobWatch", "BytesCamera", "HostActions", "PluginMonitor", "TRIGGER"]

log = logging.getLogger("octoprint.plugins.layerwatch.job")

#: what every layerwatch trigger line contains
TRIGGER = b"layerwatch snapshot layer="
#: longest wait of a trigger for the job's set-up (reading the file, locating the bed), s
SETUP_WAIT_S = 120.0


class BytesCamera(Camera):
    """A camera whose frame is the JPEG/PNG bytes a callable returns (OctoPrint's webcam snapshot).

    Parameters
    ----------
    read : callable
        ``read() -> bytes``; any exception it raises becomes a :class:`CameraError`.
    where : str
        Name of the source for messages.
    """

    def __init__(self, read: Callable[[], bytes], where: str, **kw: Any) -> None:
        kw.setdefault("retries", 0)  # the hold's time-out bounds the wait, not retries
        super().__init__(**kw)
        self._read_bytes, self.where = read, where

    def _read(self) -> np.ndarray:
        try:
            data = self._read_bytes()
        except CameraError:
            raise
        except Exception as exc:  # noqa: BLE001 - requests/provider errors: the camera is at fault
            raise CameraError(f"{self.where} failed ({type(exc).__name__}: {exc}); check the webcam's snapshot URL.") from exc
        return decode_image(data, self.where)


class _HeldCamera(Camera):
    """Wraps the job's camera: a frame that arrives after the hold timed out is refused (the head moved on)."""

    def __init__(self, inner: Camera) -> None:
        super().__init__(retries=0, stale_check=False)
        self.inner, self.where = inner, inner.where
        self.expired: Callable[[], bool] = lambda: False

    def _read(self) -> np.ndarray:
        img = self.inner.grab()
        if self.expired():
            raise CameraError(f"{self.where}: the frame came after the hold timed out, so the head may have "
                              "moved on; it was not analysed (raise hold_timeout_s or check the camera).")
        return img


class HostActions:
    """The printer as :class:`Monitor` drives it: ``pause()`` and ``cancel()`` through OctoPrint."""

    def __init__(self, pause: Callable[[], None], cancel: Callable[[], None]) -> None:
        self.pause, self.cancel = pause, cancel


class PluginMonitor(Monitor):
    """:class:`Monitor` that also reports every finished layer (result and overlay PNG) to ``on_result``."""

    def __init__(self, *args: Any, on_result: Callable[[LayerResult, bytes | None], None], **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.on_result = on_result

    def finish_layer(self, trigger: SnapshotTrigger, res: LayerResult, top: np.ndarray | None = None) -> LayerResult:
        res = super().finish_layer(trigger, res, top)
        png = None
        if res.status == "ok" and top is not None and res.heatmap is not None:
            try:
                png = overlay_png(self.pipeline, res, top)
            except (LayerwatchError, ValueError) as exc:
                log.warning("overlay of layer %d not drawn: %s", res.layer, exc)
        try:
            self.on_result(res, png)
        except Exception:  # noqa: BLE001 - the tab must not stop the monitor
            log.exception("reporting layer %d failed", res.layer)
        return res


def overlay_png(pipeline: Any, res: LayerResult, top: np.ndarray) -> bytes:
    """PNG of the failing regions over the top view of ``res``'s photo."""
    rgb = overlay_image(top, res, pipeline.topview, pipeline.reference(res.layer).footprint)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


class JobWatch:
    """Watch one print (see the module notes).

    Parameters
    ----------
    options : mapping
        Validated plugin settings (:func:`~octoprint_layerwatch.options.validate_options`).
    gcode_path : Path
        The printed file on disk.
    host : HostActions
        Pause and cancel through OctoPrint.
    snapshot : callable
        ``snapshot() -> bytes`` from OctoPrint's webcam (used when ``options["camera"]`` is empty).
    on_result : callable
        ``on_result(result, overlay_png_or_None)`` after every layer.
    """

    def __init__(self, options: Mapping[str, Any], gcode_path: Path, host: HostActions,
                 snapshot: Callable[[], bytes], on_result: Callable[[LayerResult, bytes | None], None]) -> None:
        self.options, self.gcode_path, self.host = dict(options), Path(gcode_path), host
        self.snapshot, self.on_result = snapshot, on_result
        self.monitor: PluginMonitor | None = None
        self.error: str | None = None
        self.n_layers = 0
        self._camera: _HeldCamera | None = None
        self._ready = threading.Event()

    def setup(self) -> None:
        """Read the job, resolve the settings, locate the camera, build the pipeline (on the worker)."""
        try:
            self.monitor = self._build()
        except (LayerwatchError, OSError) as exc:
            self.error = str(exc)
            log.error("layerwatch cannot watch %s: %s", self.gcode_path.name, exc)
        finally:
            self._ready.set()

    def _build(self) -> PluginMonitor:
        o = self.options
        data = self.gcode_path.read_bytes()
        if TRIGGER not in data:
            raise LayerwatchError(f"{self.gcode_path.name} has no layerwatch snapshot triggers; prepare it with "
                                  "`layerwatch gcode prepare --profile octoprint` and print the prepared file.")
        if not o["camera_model"]:
            raise LayerwatchError("no camera model set; make one with `layerwatch calibrate` and set its path "
                                  "in the layerwatch settings.")
        cfg = job_config(o)
        toolpath = read_toolpath(data)
        self.n_layers = toolpath.n_layers
        cam = CameraModel.load(o["camera_model"])
        if not cam.has_pose:
            if not o["bed_photo"]:
                raise LayerwatchError("the camera model has no bed pose; set a bed photo (markers visible) "
                                      "or run `layerwatch calibrate` with the bed in view.")
            photo = cv2.imread(o["bed_photo"], cv2.IMREAD_COLOR)
            if photo is None:
                raise LayerwatchError(f"bed photo {o['bed_photo']} is not a readable image.")
            cam = locate_bed(cam, photo, cfg.markers, cfg.topview.topview())
        source = open_camera(o["camera"]) if o["camera"] else BytesCamera(self.snapshot, "OctoPrint's webcam")
        self._camera = _HeldCamera(source)
        pipe = LayerPipeline(toolpath, cam, cfg)
        return PluginMonitor(self.host, self._camera, pipe, PausePolicy(cfg.policy), notifier=Notifier(cfg.notify),
                             wait_for_verdict=cfg.policy.wait_for_verdict, on_result=self.on_result)

    def take(self, trigger: SnapshotTrigger, expired: Callable[[], bool]) -> None:
        """Photograph ``trigger``'s layer and queue its analysis (the hold's ``take``; blocks until the frame is in)."""
        if not self._ready.wait(SETUP_WAIT_S) or self.monitor is None or self._camera is None:
            return
        if expired():
            return
        self._camera.expired = expired
        self.monitor.handle_trigger(trigger)

    def close(self) -> None:
        """Finish the queued analysis (blocks; call off OctoPrint's threads)."""
        if self.monitor is not None:
            self.monitor.close()
