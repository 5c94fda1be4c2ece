"""Job configuration: one TOML file, validated, with defaults for everything.

Example ``layerwatch.toml``::

    [topview]
    px_per_mm = 6.67
    width_mm = 90
    center_mm = [110, 100]

    [analysis]
    metric = "cosine"
    threshold = 0.7

Each section is a pydantic model that lives next to the code that uses it.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from pydantic import Field, ValidationError

from layerwatch.analysis.frame_quality import FrameQualitySettings
from layerwatch.analysis.settings import AnalysisSettings
from layerwatch.errors import ConfigError
from layerwatch.gcode.settings import PrinterProfile, SnapshotSettings
from layerwatch.geometry.settings import MarkerSettings, TopViewSettings
from layerwatch.monitor.health import FaultSettings
from layerwatch.monitor.printers.keys import HostSettings
from layerwatch.monitor.settings import NotifySettings, PolicySettings
from layerwatch.render.settings import RenderSettings
from layerwatch.settings_base import Section

__all__ = ["JobConfig", "load_config"]


class JobConfig(Section):
    """All settings of a monitored job."""

    printer: PrinterProfile = Field(default_factory=PrinterProfile)
    snapshot: SnapshotSettings = Field(default_factory=SnapshotSettings)
    topview: TopViewSettings = Field(default_factory=TopViewSettings)
    markers: MarkerSettings = Field(default_factory=MarkerSettings)
    render: RenderSettings = Field(default_factory=RenderSettings)
    analysis: AnalysisSettings = Field(default_factory=AnalysisSettings)
    policy: PolicySettings = Field(default_factory=PolicySettings)
    notify: NotifySettings = Field(default_factory=NotifySettings)
    host: HostSettings = Field(default_factory=HostSettings)
    faults: FaultSettings = Field(default_factory=FaultSettings)
    frame_quality: FrameQualitySettings = Field(default_factory=FrameQualitySettings)


def _format_validation(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err["loc"])
    return f"{where}: {err['msg']}"


def load_config(path: str | Path | None = None, defaults: dict[str, dict] | None = None,
                **overrides: dict) -> JobConfig:
    """Read a job config file (TOML); missing file or ``None`` gives the defaults.

    Parameters
    ----------
    path : str or Path or None
        TOML file. ``None`` returns defaults.
    defaults : dict of dict, optional
        Per-section values applied *under* the file: the file's own keys win
        (e.g. the evaluation's recommended settings, :mod:`layerwatch.evaluate.recommended`).
    **overrides : dict
        Per-section dictionaries merged over the file, e.g.
        ``analysis={"metric": "pearson"}``.

    Raises
    ------
    ConfigError
        Unreadable TOML or invalid values, with the key and the reason.
    """
    data: dict = {}
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"config file {p} not found; create it or drop --config.")
        try:
            data = tomllib.loads(p.read_text(encoding="utf-8", errors="replace"))
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}: not valid TOML ({exc}); fix the file.") from None
    if defaults:
        merged: dict = {k: dict(v) for k, v in defaults.items()}
        for section, values in data.items():
            if isinstance(values, dict) and isinstance(merged.get(section), dict):
                merged[section].update(values)
            else:
                merged[section] = values
        data = merged
    for section, values in overrides.items():
        data.setdefault(section, {}).update(values)
    try:
        return JobConfig.model_validate(data)
    except ValidationError as exc:
        where = f"{path}: " if path else ""
        raise ConfigError(f"{where}invalid setting {_format_validation(exc)}.") from None
