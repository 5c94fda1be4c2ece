"""The job and file API of each printer host: what it prints, and that file's G-code.

OctoPrint: ``GET /api/job`` (state and the selected file), ``/downloads/files/local/<path>``
(the file), ``/api/files/local/<path>`` (its print record). Moonraker: ``print_stats`` through
``/printer/objects/query``, ``/server/files/gcodes/<path>``, and ``gcode_move.gcode_position``
(where the head is).

Every reply is validated before use: HTTP status (through
:func:`~layerwatch.monitor.printers.base.http_request`), content type, the JSON shape and
types, and for downloads a size cap while streaming and the declared length. Any failure is a
:class:`~layerwatch.errors.PrinterError` naming the host, the path and what to check.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import numpy as np

from layerwatch.errors import ConfigError, PrinterError
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.monitor.printers.bambu import BambuPrinter
from layerwatch.monitor.printers.base import Printer, error_detail, http_request
from layerwatch.monitor.printers.keys import resolve_key, split_url_key
from layerwatch.monitor.printers.moonraker import _STATES as MOONRAKER_STATES
from layerwatch.monitor.printers.octoprint import _STATES as OCTOPRINT_STATES
from layerwatch.monitor.printers.prusalink import PrusaLinkPrinter

__all__ = ["PrintJob", "JobHost", "OctoPrintJobs", "MoonrakerJobs", "job_host", "MAX_GCODE_BYTES", "HOST_PRINTERS",
           "open_host_printer"]

#: largest G-code download accepted, bytes (a 500 MB file is an hours-long print of a big part)
MAX_GCODE_BYTES = 512 * 1024 * 1024

#: content types a G-code download may have (hosts send G-code as text or as bytes)
_GCODE_TYPES = ("text/plain", "text/x-gcode", "application/octet-stream", "application/x-gcode", "text/x.gcode")


@dataclass(frozen=True)
class PrintJob:
    """The job a host is printing.

    Attributes
    ----------
    host : str
        ``"octoprint"`` or ``"moonraker"``.
    path : str
        File path in the host's storage (OctoPrint ``local`` origin, Moonraker ``gcodes`` root).
    origin : str
        Storage (``"local"``, ``"sdcard"``, ``"gcodes"``).
    size : int or None
        Size the host reports, bytes.
    """

    host: str
    path: str
    origin: str = "local"
    size: int | None = None

    @property
    def name(self) -> str:
        """File name without folders."""
        return self.path.rsplit("/", 1)[-1]



class JobHost(ABC):
    """What the watcher asks of a printer host: the current job and its file.

    Parameters
    ----------
    http : httpx.Client
        The connector's client (``base_url`` and credentials set).
    """

    kind = "host"
    printer_name = "host"

    def __init__(self, http: httpx.Client) -> None:
        self.http = http

    def _json(self, method: str, path: str, **kw: Any) -> Any:
        r = http_request(self.http, method, path, printer=self.printer_name, credential="the request",
                         auth_hint="check the API key in the printer URL", **kw)
        if "json" not in r.headers.get("content-type", ""):
            raise PrinterError(f"{self.printer_name} {path} answered {r.headers.get('content-type') or 'no content type'}"
                               f", not JSON ({error_detail(r.text, 60)}); check the printer URL points at "
                               f"{self.printer_name}.")
        try:
            return r.json()
        except ValueError:
            raise PrinterError(f"{self.printer_name} {path} answered invalid JSON; check the printer URL.") from None

    @abstractmethod
    def current(self) -> tuple[str, PrintJob | None]:
        """The host's state (``printing``, ``paused``, ``idle``...) and its job (``None`` when there is none)."""

    @abstractmethod
    def download_path(self, job: PrintJob) -> str:
        """URL path of the job's file."""

    def position(self) -> tuple[float, float, float] | None:
        """The head's position as the printer reports it (G-code coordinates, mm), or ``None`` if it cannot tell."""
        return None

    def last_outcome(self, job: PrintJob) -> str | None:
        """How ``job``, which just left the host, ended (``"done"``, ``"cancelled"``) where the state alone says idle."""
        return None

    def download(self, job: PrintJob, max_bytes: int = MAX_GCODE_BYTES) -> bytes:
        """The job's G-code, streamed with a size cap.

        Raises
        ------
        PrinterError
            Unreachable host, HTTP error, a web page or JSON instead of G-code, an empty file, a
            file larger than ``max_bytes`` or a body shorter than its ``Content-Length``.
        """
        path = self.download_path(job)
        where = f"{self.printer_name} {path}"
        try:
            with self.http.stream("GET", path) as r:
                if r.status_code >= 400:
                    r.read()
                    raise PrinterError(f"{where} failed with HTTP {r.status_code}: {error_detail(r.text)}; "
                                       "check that the file still exists on the host.")
                ctype = r.headers.get("content-type", "").split(";")[0].strip().lower()
                if ctype and not ctype.startswith(_GCODE_TYPES):
                    raise PrinterError(f"{where} sent {ctype}, not G-code; check the printer URL.")
                declared = r.headers.get("content-length")
                if declared is not None and (not declared.isdigit() or int(declared) > max_bytes):
                    raise PrinterError(f"{where}: file of {declared} bytes is over the {max_bytes} byte limit.")
                chunks, total = [], 0
                for chunk in r.iter_bytes():
                    total += len(chunk)
                    if total > max_bytes:
                        raise PrinterError(f"{where}: file larger than the {max_bytes} byte limit.")
                    chunks.append(chunk)
        except httpx.HTTPError as exc:
            raise PrinterError(f"{where}: download failed ({type(exc).__name__}); check the host.") from exc
        if declared is not None and total != int(declared):
            raise PrinterError(f"{where}: got {total} of {declared} bytes; the download was cut short.")
        if total == 0:
            raise PrinterError(f"{where}: the file is empty.")
        return b"".join(chunks)


def _field(obj: Any, key: str, kinds: type | tuple[type, ...], where: str, optional: bool = True) -> Any:
    """``obj[key]`` checked against ``kinds`` (``None`` allowed when ``optional``)."""
    if not isinstance(obj, dict):
        raise PrinterError(f"{where}: expected a JSON object, got {type(obj).__name__}.")
    value = obj.get(key)
    if value is None and optional:
        return None
    if not isinstance(value, kinds) or isinstance(value, bool):
        raise PrinterError(f"{where}: field {key!r} is {type(value).__name__}, not {kinds}; is this the right host?")
    return value


class OctoPrintJobs(JobHost):
    """OctoPrint's ``/api/job`` and ``/downloads/files/local/<path>``."""

    kind = printer_name = "octoprint"

    def current(self) -> tuple[str, PrintJob | None]:
        body = self._json("GET", "/api/job")
        text = str(_field(body, "state", str, "OctoPrint /api/job", optional=False)).lower()
        state = next((v for k, v in OCTOPRINT_STATES.items() if text.startswith(k)), "idle")
        job = _field(body, "job", dict, "OctoPrint /api/job")
        file = _field(job, "file", dict, "OctoPrint /api/job job") if job else None
        path = _field(file, "path", str, "OctoPrint /api/job job.file") if file else None
        if not path:
            return state, None
        origin = _field(file, "origin", str, "OctoPrint /api/job job.file") or "local"
        size = _field(file, "size", int, "OctoPrint /api/job job.file")
        return state, PrintJob("octoprint", path, origin, size)

    def last_outcome(self, job: PrintJob) -> str | None:
        """OctoPrint goes back to "Operational" after both; the file's print record (``prints.last.success``) tells.

        OctoPrint records a cancelled and a failed print alike (``success: false``): both give ``"cancelled"``.
        """
        if job.origin != "local":
            return None
        body = self._json("GET", "/api/files/local/" + quote(job.path, safe="/"))
        prints = _field(body, "prints", dict, "OctoPrint file record")
        last = _field(prints, "last", dict, "OctoPrint file record prints") if prints else None
        ok = last.get("success") if last else None
        return None if not isinstance(ok, bool) else ("done" if ok else "cancelled")

    def download_path(self, job: PrintJob) -> str:
        if job.origin != "local":
            raise PrinterError(f"{job.name} is printed from the printer's SD card, which OctoPrint cannot read back; "
                                 "upload the prepared file to OctoPrint and print it from there.")
        return "/downloads/files/local/" + quote(job.path, safe="/")


class MoonrakerJobs(JobHost):
    """Moonraker's ``print_stats`` and ``/server/files/gcodes/<path>``."""

    kind = printer_name = "moonraker"

    def current(self) -> tuple[str, PrintJob | None]:
        body = self._json("GET", "/printer/objects/query", params={"print_stats": "state,filename"})
        status = _field(_field(body, "result", dict, "Moonraker objects query", optional=False),
                        "status", dict, "Moonraker objects query result", optional=False)
        stats = _field(status, "print_stats", dict, "Moonraker status", optional=False)
        state = MOONRAKER_STATES.get(str(_field(stats, "state", str, "Moonraker print_stats", optional=False)), "idle")
        path = _field(stats, "filename", str, "Moonraker print_stats")
        return state, (PrintJob("moonraker", path, "gcodes") if path else None)

    def download_path(self, job: PrintJob) -> str:
        return "/server/files/gcodes/" + quote(job.path, safe="/")

    def position(self) -> tuple[float, float, float]:
        """Klipper's ``gcode_move.gcode_position`` (X, Y, Z in G-code coordinates, mm).

        Raises
        ------
        PrinterError
            Unreachable host, or a reply without three finite numbers.
        """
        body = self._json("GET", "/printer/objects/query", params={"gcode_move": "gcode_position"})
        status = _field(_field(body, "result", dict, "Moonraker objects query", optional=False),
                        "status", dict, "Moonraker objects query result", optional=False)
        pos = _field(_field(status, "gcode_move", dict, "Moonraker status", optional=False),
                     "gcode_position", list, "Moonraker gcode_move", optional=False)
        try:
            xyz = tuple(float(v) for v in pos[:3])
        except (TypeError, ValueError):
            xyz = ()
        if len(xyz) != 3 or not all(np.isfinite(xyz)):
            raise PrinterError(f"Moonraker gcode_move.gcode_position is {pos!r}, not a position; is Klippy ready?")
        return xyz  # type: ignore[return-value]


def job_host(printer: Printer) -> JobHost:
    """The :class:`JobHost` for a connector (uses the connector's HTTP client and credentials).

    Raises
    ------
    ConfigError
        The printer is not an OctoPrint or Moonraker connector (the virtual printer has no host).
    """
    cls = {"octoprint": OctoPrintJobs, "moonraker": MoonrakerJobs}.get(printer.name)
    http = getattr(printer, "_http", None)
    if cls is None or http is None:
        raise ConfigError(f"--printer {printer.name} has no job host to follow; use octoprint://... or moonraker://..., "
                          "or give the job with --gcode.")
    return cls(http)



#: printer URL schemes whose connector follows layers from the host's own status (no trigger echo)
HOST_PRINTERS: dict[str, type[PrusaLinkPrinter] | type[BambuPrinter]] = {"prusalink": PrusaLinkPrinter,
                                                                         "bambu": BambuPrinter}


def open_host_printer(kind: str, spec: str, gcode: bytes | None = None, *, key_file: Path | None = None,
                      host: Any = None) -> Printer:
    """A PrusaLink or Bambu Lab connector from its URL, with its secret from a key file, the environment or the job file.

    Parameters
    ----------
    kind : str
        ``"prusalink"`` or ``"bambu"`` (:data:`HOST_PRINTERS`).
    spec : str
        ``prusalink://host?user=NAME`` or ``bambu://host?serial=SERIAL``.
    gcode : bytes, optional
        The job's G-code: its layer tops name the layers the connector reports.
    key_file : Path, optional
        ``--key-file`` (the PrusaLink password or the Bambu access code on its first line).
    host : HostSettings, optional
        The job file's ``[host]`` section.

    Raises
    ------
    ConfigError, PrinterError
        A bad URL, no secret, an unreadable key file.
    """
    file = key_file or (Path(host.key_file) if host is not None and host.key_file else None)
    config_key = host.api_key.get_secret_value() if host is not None and host.api_key else None
    secret, source = resolve_key(kind, spec, key_file=file, config_key=config_key)
    logging.getLogger("layerwatch.monitor").info("%s password/access code from: %s", kind, source)
    layer_z = [layer.z for layer in read_toolpath(gcode).layers] if gcode else None
    return HOST_PRINTERS[kind](split_url_key(spec)[0], secret, layer_z=layer_z)


def printer_camera(printer: Printer, spec: Any) -> tuple[Any, CameraModel]:
    """The printer's own camera (``--camera printer``: PrusaLink's snapshot, a Bambu P1/A1's stream) and its model.

    Parameters
    ----------
    printer : Printer
        A connector with a ``camera(**kw)`` method.
    spec : CameraSpec
        ``model`` (camera.toml, required) and ``settle_s``.

    Raises
    ------
    ConfigError
        The connector has no camera, or no ``--camera-model`` was given.
    """
    make = getattr(printer, "camera", None)
    if make is None:
        raise ConfigError(f"--camera printer: {printer.name} has no camera layerwatch can read; give --camera http://... "
                          "(a snapshot or MJPEG URL).")
    if spec.model is None:
        raise ConfigError("--camera-model camera.toml is needed with a real camera; make one with `layerwatch calibrate`.")
    return make(settle_s=spec.settle_s), CameraModel.load(spec.model)
