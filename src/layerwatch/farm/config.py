"""``farm.toml``: the printers of a farm and how the service runs them, validated at the edge.

Example::

    [farm]                      # optional
    workers = 2                 # analysis workers shared by all printers (local threads)
    queue_frames = 2            # frames a printer may have waiting; older ones are dropped
    scheduler = "tcp://host:8786"   # optional: run the per-layer work on a Dask cluster
    images = "images"           # real printers' layer images (default: beside the history database)
    keep_mb = 2000              # image retention: at most this many MB of job folders...
    keep_jobs = 200             # ...and at most this many jobs (oldest deleted first)

    [[printers]]
    name = "p01"
    printer = "virtual"         # or octoprint://host:port?key=..., moonraker://host:port
    camera = "sim"              # or a snapshot/stream URL, file:DIR, /dev/videoN
    layer_seconds = 1.0         # virtual printer: time per layer, s
    failure = "spaghetti"       # sim camera: optional injected failure
    onset = 8                   # sim camera: first failed layer
    park_tolerance = 1.0        # real printer: frames taken off the park spot (mm) are rejected; false: no check
    # gcode, camera_model, bed_photo, config (job.toml): paths, relative to farm.toml
    [printers.settings]         # overrides of the job settings (highest precedence)
    policy = { pause_ratio = 0.05 }

Every mistake is one :class:`~layerwatch.errors.ConfigError` line naming the
printer and the key (the CLI exits 2): unknown keys, duplicate names,
non-finite or out-of-range numbers, unknown printer or camera kinds.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from layerwatch.errors import ConfigError
from layerwatch.simulate.failures import FAILURE_TYPES

__all__ = ["FarmConfig", "PrinterSpec", "load_farm", "parse_farm"]

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_PRINTER = re.compile(r"^(virtual(:.+)?|octoprint://.+|moonraker://.+)$")
_CAMERA = re.compile(r"^(sim|https?://.+|file:.+|/dev/video\d+)$")
_SETTINGS_SECTIONS = ("topview", "render", "analysis", "policy", "notify", "markers", "snapshot", "printer")


@dataclass(frozen=True)
class PrinterSpec:
    """One ``[[printers]]`` table, validated (paths resolved against the farm file's folder).

    Attributes
    ----------
    name : str
        Unique printer name (letters, digits, ``_.-``; at most 64 characters).
    printer : str
        ``"virtual"``, ``"virtual:FILE"``, ``"octoprint://host:port?key=..."`` or ``"moonraker://host:port"``.
    camera : str
        ``"sim"``, a snapshot/stream URL, ``"file:DIR"`` or ``"/dev/videoN"``.
    gcode, camera_model, bed_photo, config : Path or None
        The job's G-code (a virtual printer's default: the bundled example part; a real
        printer without it picks up every job its host starts and downloads its G-code), camera intrinsics/pose
        (``camera.toml``), a photo of the bed with its markers (gives the pose when the
        model has none), the job settings file.
    layer_seconds : float
        Virtual printer: seconds per layer, in (0, 3600].
    failure : str or None
        Sim camera: injected failure type (one of ``FAILURE_TYPES``).
    onset : int
        Sim camera: first failed layer, >= 1.
    seed : int
        Sim camera: random seed.
    settle_s : float
        Wait after the trigger before the photo, s, in [0, 60].
    wait_for_verdict : bool
        Hold the printer until the layer is analysed.
    park_tolerance_mm : float or None
        Real printer: reject frames whose reported head position is farther than this from the
        layer's park spot, mm (as ``layerwatch monitor --park-tolerance``); ``None``: no check.
    settings : dict of dict
        Per-section job settings overriding every other source.
    """

    name: str
    printer: str = "virtual"
    camera: str = "sim"
    gcode: Path | None = None
    camera_model: Path | None = None
    bed_photo: Path | None = None
    config: Path | None = None
    layer_seconds: float = 1.0
    failure: str | None = None
    onset: int = 15
    seed: int = 1
    settle_s: float = 0.0
    wait_for_verdict: bool = False
    park_tolerance_mm: float | None = 1.0
    settings: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    @property
    def is_virtual(self) -> bool:
        """The printer is layerwatch's own virtual printer."""
        return self.printer == "virtual" or self.printer.startswith("virtual:")

    @property
    def follows_jobs(self) -> bool:
        """A real printer without ``gcode``: the service picks up each job the host starts."""
        return not self.is_virtual and self.gcode is None

    @property
    def safe_printer(self) -> str:
        """The printer URL without its query (API keys never leave the service)."""
        return self.printer.split("?", 1)[0]


@dataclass(frozen=True)
class FarmConfig:
    """A validated farm file.

    Attributes
    ----------
    printers : tuple of PrinterSpec
        In file order; names are unique.
    workers : int
        Shared analysis workers (threads; Dask tasks in flight with a scheduler), 1..256.
    queue_frames : int
        Frames a printer may have waiting for a worker, 1..64; when full the oldest is dropped.
    scheduler : str or None
        Dask scheduler address (``tcp://host:8786``) or ``"local"``; ``None``: local threads.
    images : Path or None
        Folder of the real printers' layer images (:class:`~layerwatch.monitor.artifacts.ArtifactStore`);
        ``None``: beside the history database.
    keep_mb, keep_jobs : float or int or None
        Image retention limits (``None``: none).
    """

    printers: tuple[PrinterSpec, ...]
    workers: int = 2
    queue_frames: int = 2
    scheduler: str | None = None
    images: Path | None = None
    keep_mb: float | None = None
    keep_jobs: int | None = None


def _where(printer: str | None, key: str) -> str:
    return f"printer {printer!r}: {key}" if printer else key


def _number(raw: Any, where: str, lo: float, hi: float, *, integer: bool = False) -> float:
    kind = "an integer" if integer else "a number"
    ok = isinstance(raw, int) if integer else isinstance(raw, (int, float))
    if isinstance(raw, bool) or not ok:
        raise ConfigError(f"{where} must be {kind} in [{lo:g}, {hi:g}], not {raw!r}.")
    if not math.isfinite(raw) or not lo <= raw <= hi:
        raise ConfigError(f"{where} = {raw!r} is out of range; use {kind} in [{lo:g}, {hi:g}].")
    return raw


def _text(raw: Any, where: str, pattern: re.Pattern[str], hint: str) -> str:
    if not isinstance(raw, str) or not pattern.match(raw):
        shown = raw.split("?", 1)[0] if isinstance(raw, str) else raw  # never echo an API key
        raise ConfigError(f"{where} = {shown!r} is not valid; use {hint}.")
    return raw


def _path(raw: Any, where: str, base: Path, *, folder: bool = False) -> Path:
    if not isinstance(raw, str) or not raw:
        raise ConfigError(f"{where} must be a path (string), not {raw!r}.")
    p = Path(raw).expanduser()
    p = p if p.is_absolute() else base / p
    if not (p.is_dir() if folder else p.is_file()):
        raise ConfigError(f"{where} = {raw!r}: no such {'folder' if folder else 'file'} ({p}).")
    return p


def _settings(raw: Any, where: str) -> dict[str, dict[str, Any]]:
    if not isinstance(raw, dict):
        raise ConfigError(f"{where} must be a table of sections ({', '.join(_SETTINGS_SECTIONS)}).")
    for section, values in raw.items():
        if section not in _SETTINGS_SECTIONS or not isinstance(values, dict):
            raise ConfigError(f"{where}.{section} is not a settings section; use one of {', '.join(_SETTINGS_SECTIONS)}.")
        for key, value in values.items():
            if isinstance(value, float) and not math.isfinite(value):
                raise ConfigError(f"{where}.{section}.{key} = {value!r} is not finite; give a finite number.")
    return raw


_FARM_KEYS = ("workers", "queue_frames", "scheduler", "images", "keep_mb", "keep_jobs")


def _folder(raw: Any, where: str, base: Path) -> Path:
    """A folder for output (created when missing), relative to ``base``."""
    if not isinstance(raw, str) or not raw:
        raise ConfigError(f"{where} must be a folder path (string), not {raw!r}.")
    p = Path(raw).expanduser()
    p = p if p.is_absolute() else base / p
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{where} = {raw!r}: cannot create {p} ({exc.strerror}); pick a writable folder.") from None
    return p


_PRINTER_KEYS = ("name", "printer", "camera", "gcode", "camera_model", "bed_photo", "config", "layer_seconds",
                 "failure", "onset", "seed", "settle", "wait_for_verdict", "park_tolerance", "settings")


def _printer(raw: Any, index: int, base: Path) -> PrinterSpec:
    if not isinstance(raw, dict):
        raise ConfigError(f"printers[{index}] must be a [[printers]] table.")
    name = raw.get("name")
    if not isinstance(name, str) or not _NAME.match(name):
        raise ConfigError(f"printers[{index}]: name = {name!r} is not valid; use 1-64 letters, digits, '_', '.', '-'.")
    for key in raw:
        if key not in _PRINTER_KEYS:
            raise ConfigError(f"printer {name!r}: unknown key {key!r}; use {', '.join(_PRINTER_KEYS)}.")
    w = lambda key: _where(name, key)  # noqa: E731
    kw: dict[str, Any] = {"name": name}
    if "printer" in raw:
        kw["printer"] = _text(raw["printer"], w("printer"), _PRINTER,
                              '"virtual", "octoprint://host:port?key=KEY" or "moonraker://host:port"')
    if "camera" in raw:
        kw["camera"] = _text(raw["camera"], w("camera"), _CAMERA,
                             '"sim", an http(s):// snapshot or stream URL, "file:DIR" or "/dev/videoN"')
        if kw["camera"].startswith("file:"):
            _path(kw["camera"][5:], w("camera"), base, folder=True)
    for key in ("gcode", "camera_model", "bed_photo", "config"):
        if key in raw:
            kw[key] = _path(raw[key], w(key), base)
    if "layer_seconds" in raw:
        kw["layer_seconds"] = float(_number(raw["layer_seconds"], w("layer_seconds"), 0.001, 3600))
    if "failure" in raw:
        if raw["failure"] not in FAILURE_TYPES:
            raise ConfigError(f"{w('failure')} = {raw['failure']!r} is unknown; use one of {', '.join(FAILURE_TYPES)}.")
        kw["failure"] = raw["failure"]
    if "onset" in raw:
        kw["onset"] = int(_number(raw["onset"], w("onset"), 1, 100_000, integer=True))
    if "seed" in raw:
        kw["seed"] = int(_number(raw["seed"], w("seed"), 0, 2**32 - 1, integer=True))
    if "settle" in raw:
        kw["settle_s"] = float(_number(raw["settle"], w("settle"), 0, 60))
    if "wait_for_verdict" in raw:
        if not isinstance(raw["wait_for_verdict"], bool):
            raise ConfigError(f"{w('wait_for_verdict')} must be true or false.")
        kw["wait_for_verdict"] = raw["wait_for_verdict"]
    if "park_tolerance" in raw:
        tol = raw["park_tolerance"]
        if tol is not False and (isinstance(tol, bool) or not isinstance(tol, (int, float)) or not math.isfinite(tol)
                                 or not 0 < tol <= 100):
            raise ConfigError(f"{w('park_tolerance')} = {tol!r}: give a distance in mm in (0, 100], or false for no check.")
        kw["park_tolerance_mm"] = None if tol is False else float(tol)
    if "settings" in raw:
        kw["settings"] = _settings(raw["settings"], w("settings"))
    spec = PrinterSpec(**kw)
    if spec.camera != "sim" and spec.camera_model is None:
        raise ConfigError(f"{w('camera_model')} is needed with camera {spec.camera.split('?', 1)[0]!r}; "
                          "make one with `layerwatch calibrate`.")
    return spec


def parse_farm(data: Mapping[str, Any], base: Path) -> FarmConfig:
    """Validate the parsed TOML of a farm file.

    Parameters
    ----------
    data : mapping
        The TOML document (``[farm]`` and ``[[printers]]``).
    base : Path
        Folder relative paths are resolved against.

    Returns
    -------
    FarmConfig

    Raises
    ------
    ConfigError
        One line naming the printer and key at fault.
    """
    for key in data:
        if key not in ("farm", "printers"):
            raise ConfigError(f"unknown table {key!r}; a farm file has [farm] and [[printers]].")
    farm = data.get("farm", {})
    if not isinstance(farm, dict):
        raise ConfigError("farm must be a [farm] table.")
    kw: dict[str, Any] = {}
    for key in farm:
        if key not in _FARM_KEYS:
            raise ConfigError(f"farm: unknown key {key!r}; use {', '.join(_FARM_KEYS)}.")
    if "workers" in farm:
        kw["workers"] = int(_number(farm["workers"], "farm: workers", 1, 256, integer=True))
    if "queue_frames" in farm:
        kw["queue_frames"] = int(_number(farm["queue_frames"], "farm: queue_frames", 1, 64, integer=True))
    if "scheduler" in farm:
        kw["scheduler"] = _text(farm["scheduler"], "farm: scheduler", re.compile(r"^(local|tcp://.+|tls://.+)$"),
                                '"tcp://host:8786" or "local"')
    if "images" in farm:
        kw["images"] = _folder(farm["images"], "farm: images", base)
    if "keep_mb" in farm:
        kw["keep_mb"] = float(_number(farm["keep_mb"], "farm: keep_mb", 1, 1e9))
    if "keep_jobs" in farm:
        kw["keep_jobs"] = int(_number(farm["keep_jobs"], "farm: keep_jobs", 1, 1e6, integer=True))
    raw = data.get("printers")
    if not isinstance(raw, list) or not raw:
        raise ConfigError("no [[printers]] table; add one per printer (name, printer, camera...).")
    printers = [_printer(p, i, base) for i, p in enumerate(raw)]
    seen: set[str] = set()
    for p in printers:
        if p.name in seen:
            raise ConfigError(f"printer {p.name!r}: name is used twice; give every printer its own name.")
        seen.add(p.name)
    return FarmConfig(tuple(printers), **kw)


def load_farm(path: str | Path) -> FarmConfig:
    """Read and validate ``farm.toml`` (see :func:`parse_farm`).

    Raises
    ------
    ConfigError
        Unreadable file, TOML syntax error, or an invalid table (one line).
    """
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read farm file {path}: {exc.strerror}; check the path.") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path} is not valid TOML ({exc}); fix the syntax.") from None
    return parse_farm(data, path.parent)
