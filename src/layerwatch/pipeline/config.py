"""Job configuration and the one settings resolver.

Every verb gets its settings from :func:`resolve_config`, which merges, per
key, lowest precedence first:

1. ``default``: the sections' built-in values (the paper's: cosine, T_S 0.7,
   5 mm footprint margin, pause a% > 10 %);
2. ``recommended``: :data:`RECOMMENDED`, the values the evaluation on
   simulated prints chose (``docs/evaluation/README.md``: jaccard, T_S 0.20,
   pause a% > 2.5 %...); left out by ``--paper-settings``;
3. ``dashboard``: keys saved in the dashboard (``monitor --history``);
4. ``gcode``: values derived from the job's G-code when no job file is given
   (the observed square centred on the part);
5. ``file``: the job config file (``-c job.toml``);
6. ``flag``: command-line options.

It records where each value came from (:attr:`ResolvedConfig.sources`);
``layerwatch config show`` prints both.

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
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError

from layerwatch.analysis.check_settings import (
    BedCheckSettings,
    ExtrusionSettings,
    FirstLayerSettings,
)
from layerwatch.analysis.frame_quality import FrameQualitySettings
from layerwatch.analysis.layer_change import LayerChangeSettings
from layerwatch.analysis.settings import AnalysisSettings, SceneSettings
from layerwatch.errors import ConfigError
from layerwatch.gcode.settings import PrinterProfile, SnapshotSettings
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.settings import MarkerSettings, TopViewSettings
from layerwatch.pipeline.policy import NotifySettings, PolicySettings
from layerwatch.pipeline.watch_settings import FaultSettings, HostSettings
from layerwatch.render.settings import RenderSettings
from layerwatch.settings_base import Section

__all__ = ["JobConfig", "RECOMMENDED", "SOURCES", "ResolvedConfig", "load_config", "observed_square",
           "recommended_config", "resolve_config"]

#: value sources, lowest precedence first
SOURCES = ("default", "recommended", "dashboard", "gcode", "file", "flag")

#: per-section values the evaluation on simulated prints recommends (``docs/evaluation/report.md``)
RECOMMENDED: dict[str, dict] = {
    "analysis": {"metric": "jaccard", "threshold": 0.20, "footprint_margin_mm": 0.0,
                 "presmooth_px": 1.25, "flat_tolerance": 1.5, "grow_threshold": 0.2, "grow_margin_mm": 5.0,
                 "register_mm": 0.6, "votes": "split_ties", "anomalous_area": "printed",
                 "off_colour": True},
    "policy": {"pause_ratio": 0.025, "consecutive_layers": 2, "skip_first_layers": 1, "outside_pause_mm2": 12.0},
    "scene": {"enabled": True},
    "bed_check": {"enabled": True},
    "first_layer": {"enabled": True},
    "extrusion": {"enabled": True},
    "layer_change": {"enabled": True},
}


class JobConfig(Section):
    """All settings of a monitored job."""

    printer: PrinterProfile = Field(default_factory=PrinterProfile)
    snapshot: SnapshotSettings = Field(default_factory=SnapshotSettings)
    topview: TopViewSettings = Field(default_factory=TopViewSettings)
    markers: MarkerSettings = Field(default_factory=MarkerSettings)
    render: RenderSettings = Field(default_factory=RenderSettings)
    analysis: AnalysisSettings = Field(default_factory=AnalysisSettings)
    scene: SceneSettings = Field(default_factory=SceneSettings)
    policy: PolicySettings = Field(default_factory=PolicySettings)
    notify: NotifySettings = Field(default_factory=NotifySettings)
    host: HostSettings = Field(default_factory=HostSettings)
    faults: FaultSettings = Field(default_factory=FaultSettings)
    frame_quality: FrameQualitySettings = Field(default_factory=FrameQualitySettings)
    bed_check: BedCheckSettings = Field(default_factory=BedCheckSettings)
    first_layer: FirstLayerSettings = Field(default_factory=FirstLayerSettings)
    extrusion: ExtrusionSettings = Field(default_factory=ExtrusionSettings)
    layer_change: LayerChangeSettings = Field(default_factory=LayerChangeSettings)

    def for_camera(self, camera: CameraModel) -> JobConfig:
        """This config with the top view's scale resolved for ``camera`` (``[topview] scale = "camera"``).

        Unchanged (the same object) when the scale is fixed; see
        :meth:`~layerwatch.geometry.settings.TopViewSettings.for_camera`.
        """
        tv = self.topview.for_camera(camera)
        return self if tv is self.topview else self.model_copy(update={"topview": tv})


def _format_validation(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err["loc"])
    return f"{where}: {err['msg']}"


@dataclass(frozen=True)
class ResolvedConfig:
    """The effective job config and where each value came from.

    Attributes
    ----------
    config : JobConfig
    sources : dict of str to str
        ``"section.key"`` (``"policy.kinds.spaghetti.action"`` inside tables) -> one of :data:`SOURCES`,
        for every key of every section.
    path : Path or None
        The job config file, when one was read.
    """

    config: JobConfig
    sources: dict[str, str] = field(default_factory=dict)
    path: Path | None = None

    def section_sources(self) -> dict[str, str]:
        """Per section, the sources of its values other than ``default``, highest first, joined by ``+``
        (``"file+recommended"``), or ``"default"``."""
        out: dict[str, str] = {}
        for section in JobConfig.model_fields:
            used = {v for k, v in self.sources.items() if k.split(".", 1)[0] == section and v != "default"}
            out[section] = "+".join(s for s in reversed(SOURCES) if s in used) or "default"
        return out


def _read_toml(path: str | Path) -> dict:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p} not found; create it or drop --config.")
    try:
        return tomllib.loads(p.read_text(encoding="utf-8", errors="replace"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML ({exc}); fix the file.") from None


def observed_square(bounds: tuple[float, float, float, float]) -> dict[str, dict[str, Any]]:
    """The ``gcode`` settings layer: the observed square centred on the part, 30 mm wider (at least 90 mm).

    Parameters
    ----------
    bounds : (x0, y0, x1, y1)
        The part's extent on the bed, mm (``Toolpath.bounds``).
    """
    x0, y0, x1, y1 = bounds
    side = max(90.0, max(x1 - x0, y1 - y0) + 30.0)
    return {"topview": {"center_mm": ((x0 + x1) / 2, (y0 + y1) / 2), "width_mm": side, "height_mm": side}}


def _leaf_keys(prefix: str, values: Mapping) -> list[str]:
    """Dotted keys under ``prefix`` of the keys of ``values`` and, inside tables, of their keys too
    (``policy.kinds`` and ``policy.kinds.spaghetti.action``)."""
    out = []
    for k, v in values.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if prefix:
            out.append(key)
        if isinstance(v, Mapping) and v:
            out += _leaf_keys(key, v)
    return out


def _merge_into(base: dict, values: Mapping) -> None:
    """Update ``base`` with ``values``, table by table (``[policy.kinds.detachment]`` in one layer keeps
    the other kinds and keys another layer set)."""
    for k, v in values.items():
        if isinstance(v, Mapping) and isinstance(base.get(k), dict):
            _merge_into(base[k], v)
        else:
            base[k] = dict(v) if isinstance(v, Mapping) else v


def resolve_config(
    path: str | Path | None = None,
    *,
    recommended: bool = True,
    dashboard: Mapping[str, Mapping[str, Any]] | None = None,
    gcode: Mapping[str, Mapping[str, Any]] | None = None,
    flags: Mapping[str, Mapping[str, Any]] | None = None,
) -> ResolvedConfig:
    """Merge the settings layers (module notes) into one validated :class:`JobConfig`.

    Parameters
    ----------
    path : str or Path or None
        Job config TOML; ``None``: no file layer.
    recommended : bool
        Apply :data:`RECOMMENDED` over the built-in defaults (``False`` is ``--paper-settings``).
    dashboard, gcode, flags : dict of dict, optional
        Per-section values of those layers, e.g. ``flags={"analysis": {"threshold": 0.3}}``;
        a flag left at ``None`` by the caller must be left out.

    Returns
    -------
    ResolvedConfig

    Raises
    ------
    ConfigError
        Unreadable TOML or an invalid value, naming its key and where it came from.
    """
    file = _read_toml(path) if path is not None else {}
    layers = {"recommended": RECOMMENDED if recommended else {}, "dashboard": dashboard or {},
              "gcode": gcode or {}, "file": file, "flag": flags or {}}
    data: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for name in SOURCES[1:]:
        for section, values in layers[name].items():
            if isinstance(values, Mapping) and isinstance(data.get(section, {}), dict):
                _merge_into(data.setdefault(section, {}), values)
                sources.update({key: name for key in _leaf_keys(section, values)})
            else:  # not a table: JobConfig's validation names it
                data[section] = values
                sources[section] = name
    try:
        cfg = JobConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = [str(p) for p in err["loc"]]
        origin = next((sources[k] for k in (".".join(loc[:n]) for n in range(len(loc), 0, -1)) if k in sources),
                      next((v for k, v in sources.items() if k.startswith(".".join(loc) + ".")), "file"))
        if origin == "file":
            raise ConfigError(f"{path}: invalid setting {_format_validation(exc)}.") from None
        kind = {"flag": "command-line", "gcode": "G-code derived"}.get(origin, origin)
        raise ConfigError(f"invalid {kind} setting {_format_validation(exc)}.") from None
    for key in _leaf_keys("", cfg.model_dump(mode="json")):
        sources.setdefault(key, "default")
    return ResolvedConfig(cfg, sources, None if path is None else Path(path))


def load_config(path: str | Path | None = None, **flags: dict) -> JobConfig:
    """The job file over the built-in (paper) defaults: ``resolve_config(path, recommended=False, flags=flags)``."""
    return resolve_config(path, recommended=False, flags=flags).config


def recommended_config(path: str | Path | None = None, **flags: dict) -> JobConfig:
    """The job file over :data:`RECOMMENDED` over the defaults: ``resolve_config(path, flags=flags)``."""
    return resolve_config(path, flags=flags).config
