"""The plugin's settings: defaults, validation and the layerwatch settings they resolve to.

OctoPrint stores them under ``plugins.layerwatch`` in its ``config.yaml``; the
settings tab edits them and ``POST /api/settings`` saves them. Every value is
checked here before it is stored (:func:`validate_options`): a path must name
an existing file, a number must be finite and in range, and the thresholds go
through layerwatch's own settings resolver
(:func:`layerwatch.pipeline.config.resolve_config`), which checks them as the
command line's ``--set``: the job file's keys, then these thresholds.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from layerwatch.errors import ConfigError
from layerwatch.pipeline.config import JobConfig, resolve_config

__all__ = ["DEFAULTS", "THRESHOLDS", "validate_options", "job_config"]

#: plugin setting -> (section, key) of layerwatch's job config; an empty value leaves the job file's or the default
THRESHOLDS: dict[str, tuple[str, str]] = {
    "threshold": ("analysis", "threshold"),
    "pause_ratio": ("policy", "pause_ratio"),
    "consecutive_layers": ("policy", "consecutive_layers"),
    "action": ("policy", "action"),
}

DEFAULTS: dict[str, Any] = {
    "enabled": True,
    "camera_model": "",  # camera.toml from `layerwatch calibrate` (intrinsics, and the bed pose if known)
    "bed_photo": "",  # photo of the bed with its markers: locates the camera when camera_model has no pose
    "job_config": "",  # layerwatch job TOML (topview, analysis, policy...); empty: recommended settings
    "camera": "",  # empty: OctoPrint's snapshot webcam; else a layerwatch camera (http://..., file:DIR)
    "hold_timeout_s": 10.0,  # longest hold of the job queue per layer, s
    "threshold": None,
    "pause_ratio": None,
    "consecutive_layers": None,
    "action": None,
}

_PATHS = ("camera_model", "bed_photo", "job_config")


def _blank(v: Any) -> bool:
    return v is None or (isinstance(v, str) and not v.strip())


def _path(name: str, v: Any) -> str:
    if _blank(v):
        return ""
    if not isinstance(v, str):
        raise ConfigError(f"{name} must be a file path, got {v!r}.")
    p = Path(v).expanduser()
    if not p.is_absolute():
        raise ConfigError(f"{name} {v!r} must be an absolute path (OctoPrint's working folder is not yours).")
    if not p.is_file():
        raise ConfigError(f"{name} {v!r} does not exist or is not a file; check the path.")
    return str(p)


def _timeout(v: Any) -> float:
    try:
        t = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"hold_timeout_s must be a number of seconds, got {v!r}.") from None
    if not (math.isfinite(t) and 0.5 <= t <= 120):
        raise ConfigError(f"hold_timeout_s {v!r} is out of range; use 0.5 to 120 s.")
    return t


def _camera(v: Any) -> str:
    if _blank(v):
        return ""
    if not isinstance(v, str) or not v.startswith(("http://", "https://", "file:", "/dev/video", "v4l2:")):
        raise ConfigError(f"camera {v!r} is not a camera; leave it empty for OctoPrint's webcam, or use "
                          "http://...snapshot, file:DIR or /dev/videoN.")
    return v.strip()


def _flags(values: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    flags: dict[str, dict[str, Any]] = {}
    for name, (section, key) in THRESHOLDS.items():
        v = values.get(name)
        if not _blank(v):
            flags.setdefault(section, {})[key] = v
    return flags


def job_config(values: Mapping[str, Any]) -> JobConfig:
    """layerwatch's job config for validated plugin ``values``: recommended < job file < thresholds.

    Raises
    ------
    ConfigError
        Unreadable job file or a threshold out of range (one line, naming the key).
    """
    path = values.get("job_config") or None
    return resolve_config(path, recommended=True, flags=_flags(values)).config


def validate_options(values: Mapping[str, Any]) -> dict[str, Any]:
    """The complete, checked plugin settings for ``values`` (missing keys take :data:`DEFAULTS`).

    Raises
    ------
    ConfigError
        An unknown key, a missing file, a relative path, a number out of range or a threshold
        layerwatch's resolver refuses; the one-line message names the key and the fix.
    """
    unknown = sorted(set(values) - set(DEFAULTS))
    if unknown:
        raise ConfigError(f"unknown layerwatch setting(s) {', '.join(unknown)}; known: {', '.join(DEFAULTS)}.")
    out = {**DEFAULTS, **values}
    out["enabled"] = bool(out["enabled"])
    for name in _PATHS:
        out[name] = _path(name, out[name])
    out["hold_timeout_s"] = _timeout(out["hold_timeout_s"])
    out["camera"] = _camera(out["camera"])
    for name in THRESHOLDS:
        out[name] = None if _blank(out[name]) else out[name]
    cfg = job_config(out)  # raises for a bad job file or threshold
    for name, (section, key) in THRESHOLDS.items():  # stored as layerwatch read them ("0.1" -> 0.1)
        if out[name] is not None:
            out[name] = getattr(getattr(cfg, section), key)
    return out
