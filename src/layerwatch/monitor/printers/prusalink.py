"""PrusaLink connector (Prusa MK4/MK3.9/MINI/XL/CORE One): the v1 REST API with HTTP digest auth.

Endpoints (PrusaLink OpenAPI, ``spec/openapi.yaml`` of Prusa-Link-Web):

- ``GET /api/v1/status``: ``printer.state`` (``IDLE``, ``BUSY``, ``PRINTING``, ``PAUSED``,
  ``FINISHED``, ``STOPPED``, ``ERROR``, ``ATTENTION``, ``READY``), ``printer.axis_z`` (mm),
  ``job.id`` and ``job.progress`` (%);
- ``GET /api/v1/job``: the job's ``id`` and ``file.name`` (``204 No Content`` without a job);
- ``PUT /api/v1/job/{id}/pause``, ``PUT /api/v1/job/{id}/resume``, ``DELETE /api/v1/job/{id}``;
- ``GET /api/v1/cameras/snap``: the default camera's last snapshot (``204`` when there is none).

The user and password are those shown on the printer (Settings > Network > PrusaLink);
the password comes from a key file, ``LAYERWATCH_PRUSALINK_KEY`` or the job file
(:mod:`~layerwatch.monitor.printers.keys`), never from the command line.

Layer changes: PrusaLink pushes nothing and cannot echo a trigger line, so the connector
follows the printer's Z in every status poll: a layer is taken as done when Z has risen to a
new height and stayed there for ``confirm_polls`` polls (a Z-hop of a travel move is shorter
than that). The trigger's layer index counts those rises, or, with ``layer_z`` (the G-code's
layer tops), is the layer whose top is nearest the height just left. The photo is taken while the next
layer prints (no park hold), so the camera must see the part past the head.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections.abc import Iterable, Sequence
from typing import Any
from urllib.parse import parse_qsl, urlsplit

import httpx
import numpy as np

from layerwatch.errors import CameraError, ConfigError, PrinterError
from layerwatch.monitor.cameras import Camera, decode_image
from layerwatch.monitor.printers.base import Printer, PrinterStatus, SnapshotTrigger, http_request
from layerwatch.monitor.printers.keys import ENV_VARS
from layerwatch.monitor.printers.replies import field, number_field, parse_json, text_field

__all__ = ["PrusaLinkPrinter", "PrusaLinkCamera", "ZLayerTracker", "parse_status", "prusalink_target"]

log = logging.getLogger("layerwatch.monitor.prusalink")

#: PrusaLink ``printer.state`` -> PrinterStatus.state ("BUSY": a non-print action such as a
#: filament load, "ATTENTION": the printer waits for the user, e.g. a run-out)
_STATES = {"IDLE": "idle", "READY": "idle", "BUSY": "idle", "PRINTING": "printing", "PAUSED": "paused",
           "ATTENTION": "paused", "FINISHED": "finished", "STOPPED": "cancelled", "ERROR": "error"}

_HINTS = {409: "the job is not in a state for this command (already paused, or not printing)",
          404: "the job has ended or the printer's PrusaLink is too old for the v1 API (update the firmware)"}

#: smallest Z rise taken as a new layer, mm (thinner than any printable layer)
MIN_LAYER_STEP_MM = 0.04


def prusalink_target(url: str) -> tuple[str, str]:
    """The ``http://host[:port]`` base and the user of a ``prusalink://host[:port]?user=NAME`` URL.

    Raises
    ------
    ConfigError
        No host, a port out of range, or a user name with spaces or control characters.
    """
    parts = urlsplit(url)
    if parts.scheme not in ("prusalink", "http") or not parts.hostname:
        raise ConfigError(f"printer URL {parts.scheme}://{parts.hostname or ''} is not prusalink://HOST[:PORT]"
                          "?user=NAME; give the printer's address as shown in Settings > Network.")
    try:
        port = parts.port
    except ValueError:
        raise ConfigError("prusalink:// URL has a port that is not a number in 1-65535; fix the URL.") from None
    query = dict(parse_qsl(parts.query))
    user = query.get("user", "maker")
    if not user or not user.isprintable() or " " in user or len(user) > 64:
        raise ConfigError("prusalink:// ?user= must be the PrusaLink user name shown on the printer (default maker).")
    host = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
    return f"http://{host}{f':{port}' if port else ''}", user


def parse_status(body: Any) -> tuple[str, float | None, int | None, float | None]:
    """State, Z (mm), job id and progress (0-1) of a ``/api/v1/status`` reply, every field checked.

    Raises
    ------
    PrinterError
        Not an object, a field of the wrong type, a non-finite or out-of-range number.
    """
    where = "PrusaLink /api/v1/status"
    printer = field(body, "printer", dict, where, optional=False)
    raw = text_field(printer, "state", where + " printer", optional=False)
    state = _STATES.get(raw.upper(), "unknown")
    z = number_field(printer, "axis_z", where + " printer", -50.0, 2000.0)
    job = field(body, "job", dict, where) or {}
    job_id = field(job, "id", int, where + " job")
    if job_id is not None and job_id < 0:
        raise PrinterError(f"{where}: job id {job_id} is negative; unexpected host reply.")
    done = number_field(job, "progress", where + " job", 0.0, 100.0)
    return state, z, job_id, None if done is None else done / 100.0


class ZLayerTracker:
    """Layer changes from a polled Z height (hosts that neither push nor echo a trigger).

    Parameters
    ----------
    confirm_polls : int
        Polls a new, higher Z must last before it counts (a Z-hop of a travel move is shorter).
    layer_z : sequence of float, optional
        Top Z of each layer of the job's G-code, mm, ascending; then the trigger's index is the
        layer whose top is nearest the height just left. Without it, the n-th rise is layer ``n - 1``.
    """

    def __init__(self, confirm_polls: int = 2, layer_z: Sequence[float] | None = None) -> None:
        if not 1 <= int(confirm_polls) <= 100:
            raise ConfigError("confirm_polls must be 1-100.")
        self.confirm_polls = int(confirm_polls)
        self.layer_z = None if layer_z is None else [float(z) for z in layer_z]
        self.reset()

    def reset(self) -> None:
        """Forget the job (a new one starts at its first layer)."""
        self._top: float | None = None  # Z of the layer being printed
        self._candidate: float | None = None
        self._seen = 0
        self._rises = 0

    def update(self, z: float | None, printing: bool) -> SnapshotTrigger | None:
        """Feed one polled Z; the trigger of the layer just finished, if this poll confirms one."""
        if z is None or not printing:
            self._candidate, self._seen = None, 0
            return None
        if self._top is None:
            self._top = z
            return None
        if z < self._top + MIN_LAYER_STEP_MM:  # same layer, or back from a Z-hop
            self._candidate, self._seen = None, 0
            return None
        if self._candidate is None or not math.isclose(z, self._candidate, abs_tol=1e-3):
            self._candidate, self._seen = z, 0
        self._seen += 1
        if self._seen < self.confirm_polls:
            return None
        done_z, self._top, self._candidate, self._seen = self._top, z, None, 0
        self._rises += 1
        tops = self.layer_z
        if tops:  # the layer whose top is nearest (a live-Z offset shifts the reported Z a little)
            i = bisect.bisect_left(tops, done_z)
            index = min((j for j in (i - 1, i) if 0 <= j < len(tops)), key=lambda j: abs(tops[j] - done_z))
            return SnapshotTrigger(layer=index, z=done_z, source="prusalink")
        return SnapshotTrigger(layer=self._rises - 1, z=done_z, source="prusalink")


class PrusaLinkPrinter(Printer):
    """Connector for ``prusalink://host[:port]?user=NAME`` (password: ``password``).

    Parameters
    ----------
    url : str
        ``prusalink://host[:port]?user=NAME`` (``user`` defaults to ``maker``).
    password : str
        The PrusaLink password shown on the printer.
    timeout_s : float
        HTTP timeout, s.
    confirm_polls : int
        See :class:`ZLayerTracker`.
    layer_z : sequence of float, optional
        The job's layer tops, mm (see :class:`ZLayerTracker`).
    """

    name = "prusalink"

    def __init__(self, url: str, password: str | None, *, timeout_s: float = 5.0, confirm_polls: int = 2,
                 layer_z: Sequence[float] | None = None) -> None:
        super().__init__()
        self.base, self.user = prusalink_target(url)
        if not password:
            raise PrinterError(f"PrusaLink needs the password shown on the printer (Settings > Network); set "
                               f"{ENV_VARS['prusalink']}, pass --key-file FILE or put api_key in the job file's "
                               "[host] section.")
        if not (math.isfinite(timeout_s) and 0 < timeout_s <= 120):
            raise ConfigError("PrusaLink timeout must be 0-120 s.")
        self._http = httpx.Client(base_url=self.base, auth=httpx.DigestAuth(self.user, password), timeout=timeout_s)
        self._tracker = ZLayerTracker(confirm_polls, layer_z)
        self._job_id: int | None = None
        self._file: str | None = None
        self._last_layer: int | None = None

    def _req(self, method: str, path: str) -> httpx.Response:
        return http_request(self._http, method, path, printer="PrusaLink", credential="the user and password",
                            auth_hint="check ?user= and the password shown in the printer's Settings > Network",
                            status_hints=_HINTS)

    def _json(self, path: str) -> Any:
        r = self._req("GET", path)
        if r.status_code == 204:
            return None
        ctype = r.headers.get("content-type", "")
        if "json" not in ctype.lower():
            raise PrinterError(f"PrusaLink GET {path} answered {ctype.split(';')[0] or 'no content type'} instead of "
                               "JSON; check that the printer URL points at PrusaLink.")
        return parse_json(r.content, f"PrusaLink GET {path}")

    def status(self) -> PrinterStatus:
        state, z, job_id, progress = parse_status(self._json("/api/v1/status"))
        if job_id != self._job_id:  # a new job (or none): its file name, and layers from its start
            self._tracker.reset()
            self._last_layer = None
            self._file = self._job_file() if job_id is not None else None
            self._job_id = job_id
        trig = self._tracker.update(z, state == "printing")
        if trig is not None and trig.layer != self._last_layer:
            self._last_layer = trig.layer
            self._emit(trig)
        return PrinterStatus(state, self._file, self._last_layer, z, progress)

    def _job_file(self) -> str | None:
        body = self._json("/api/v1/job")
        if body is None:
            return None
        file = field(body, "file", dict, "PrusaLink /api/v1/job") or {}
        return text_field(file, "display_name", "PrusaLink job.file") or text_field(file, "name", "PrusaLink job.file")

    def _current_job(self) -> int:
        """The running job's id (asked now: the id of the last status may belong to an ended job)."""
        body = self._json("/api/v1/job")
        job_id = field(body, "id", int, "PrusaLink /api/v1/job") if body is not None else None
        if job_id is None:
            raise PrinterError("PrusaLink has no job to act on; the print has ended.")
        return job_id

    def pause(self) -> None:
        self._req("PUT", f"/api/v1/job/{self._current_job()}/pause")

    def resume(self) -> None:
        self._req("PUT", f"/api/v1/job/{self._current_job()}/resume")

    def cancel(self) -> None:
        self._req("DELETE", f"/api/v1/job/{self._current_job()}")

    def send_gcode(self, lines: str | Iterable[str]) -> None:
        """PrusaLink's API has no G-code console; refused with the alternative."""
        raise PrinterError("PrusaLink cannot run G-code sent over the network; put the commands in the "
                           "sliced file (custom G-code) instead.")

    def camera(self, **kw: Any) -> PrusaLinkCamera:
        """The printer's default camera (``/api/v1/cameras/snap``) through this connector's session."""
        return PrusaLinkCamera(self._http, **kw)

    def close(self) -> None:
        self._http.close()


class PrusaLinkCamera(Camera):
    """Snapshots of the camera attached to PrusaLink (``GET /api/v1/cameras/snap``, PNG or JPEG).

    Parameters
    ----------
    http : httpx.Client
        An authenticated client (``PrusaLinkPrinter.camera()``).
    **kw
        :class:`~layerwatch.monitor.cameras.Camera` options (retries, settle_s...).
    """

    where = "PrusaLink camera"

    def __init__(self, http: httpx.Client, **kw: Any) -> None:
        super().__init__(**kw)
        self._http = http

    def _read(self) -> np.ndarray:
        try:
            r = http_request(self._http, "GET", "/api/v1/cameras/snap", printer="PrusaLink",
                             credential="the user and password", auth_hint="check the PrusaLink password",
                             max_bytes=20_000_000)
        except PrinterError as exc:
            raise CameraError(f"{self.where}: {exc}") from None
        if r.status_code == 204 or not r.content:
            raise CameraError(f"{self.where} has no snapshot yet; check that a camera is added in PrusaLink "
                              "(Settings > Camera) and is taking pictures.")
        return decode_image(r.content, self.where)
