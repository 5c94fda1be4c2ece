"""Dashboard settings: the job config sections, bounded to documented ranges, and the pause switch.

The dashboard may change every setting of :class:`~layerwatch.pipeline.config.JobConfig`,
so every number it stores must be finite and inside :data:`RANGES` (a table
of ``(low, high, unit)`` per dotted key; tuple settings apply it to each
element). The ranges are wide enough for any real printer and camera and
narrow enough that no setting can silence the pause policy: the pause rules
always stay reachable (``pause_ratio`` at most 0.5, at most 10 consecutive
layers, areas at most 2500 mm^2, ...). Switching pausing off is a separate,
explicit act: :func:`set_pausing` (``PUT /api/pausing``, the dashboard's
"pause on failure" switch, recorded in the audit log); the settings routes
refuse to turn ``policy.action`` or ``policy.strong_action`` into
``"notify"``.
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import ValidationError

from layerwatch.analysis.failure_kinds import FAILURE_KINDS
from layerwatch.errors import ConfigError
from layerwatch.pipeline.config import JobConfig

__all__ = ["RANGES", "validate_settings", "pausing_on", "set_pausing", "validation_line", "SettingsRejected",
           "SETTINGS_KEY", "MAX_BODY"]

SETTINGS_KEY = "job_config"  # name of the dashboard's settings in the history's ``settings`` table
MAX_BODY = 1 << 20  # bytes: the largest request body the dashboard reads (settings are a few kB)

MM = (-1000.0, 2000.0, "mm")  # bed coordinates: any printer's bed fits in a 3 m box
RANGES: dict[str, tuple[float, float, str]] = {
    "printer.volume_min_mm": MM, "printer.volume_max_mm": MM,
    "printer.filament_diameter_mm": (0.5, 5.0, "mm"),
    "snapshot.every_n_layers": (1, 100, "layers"), "snapshot.retract_mm": (0.0, 20.0, "mm"),
    "snapshot.lift_mm": (0.0, 100.0, "mm"), "snapshot.park_xy_mm": MM,
    "snapshot.travel_feed_mm_min": (60.0, 60000.0, "mm/min"), "snapshot.settle_ms": (100, 60000, "ms"),
    "snapshot.z_feed_mm_min": (60.0, 60000.0, "mm/min"), "snapshot.hold_s": (0.5, 120.0, "s"),
    "snapshot.retract_feed_mm_min": (60.0, 12000.0, "mm/min"), "snapshot.light_tool": (0, 15, ""),
    "snapshot.indicator_pin": (0, 255, ""),
    "faults.printer_grace_s": (0.0, 86400.0, "s"), "faults.camera_alert_after": (1, 10000, "frames"),
    "faults.warn_interval_s": (0.0, 86400.0, "s"),
    "frame_quality.dark_p99": (0.0, 255.0, "grey level"), "frame_quality.bright_fraction": (0.01, 1.0, ""),
    "frame_quality.min_range": (0.0, 255.0, "grey levels"), "frame_quality.max_noise": (0.1, 255.0, "grey levels"),
    "frame_quality.min_sharpness": (0.0, 100.0, ""), "frame_quality.max_blockiness": (1.01, 100.0, ""),
    "frame_quality.min_change": (0.0, 255.0, "grey levels"), "frame_quality.max_repeat_spread": (0.0, 255.0, "grey levels"),
    "frame_quality.max_marker_shift_px": (0.1, 10000.0, "px"),
    "topview.px_per_mm": (0.5, 100.0, "px/mm"), "topview.width_mm": (1.0, 1000.0, "mm"),
    "topview.height_mm": (1.0, 1000.0, "mm"), "topview.center_mm": MM,
    "markers.positions_mm": MM, "markers.diameter_mm": (0.5, 50.0, "mm"),
    "markers.camera_azimuth_deg": (-360.0, 360.0, "deg"), "markers.max_pose_error_px": (0.1, 100.0, "px"),
    "render.volume_fill_layers": (0, 20, "layers"), "render.material_rgb": (0.0, 1.0, ""), "render.bed_rgb": (0.0, 1.0, ""),
    "render.light_azimuth_deg": (-360.0, 360.0, "deg"), "render.light_elevation_deg": (0.0, 90.0, "deg"),
    "render.ambient": (0.0, 1.0, ""), "render.layers_visible_below": (0, 1000, "layers"),
    "render.depth_darkening": (0.0, 1.0, ""), "render.registration_darkening": (0.0, 1.0, ""),
    "render.relief": (0.01, 20.0, ""), "render.smooth_px": (0.0, 5.0, "px"),
    "render.cavity": (0.0, 1.0, ""), "render.cavity_radius_mm": (0.01, 5.0, "mm"),
    "render.image_blur_px": (0.0, 5.0, "px"), "render.wall_light": (0.0, 1.0, ""), "render.wall_ambient": (0.0, 1.0, ""),
    "render.wall_line_contrast": (0.0, 1.0, ""), "render.markers_mm": MM, "render.marker_diameter_mm": (0.5, 50.0, "mm"),
    "render.blender_samples": (1, 4096, "samples"), "render.blender_timeout_s": (1.0, 3600.0, "s"),
    "analysis.threshold": (0.0, 1.0, ""), "analysis.cell_px": (2, 64, "px"), "analysis.block_cells": (1, 8, "cells"),
    "analysis.bins": (2, 36, "bins"), "analysis.footprint_margin_mm": (0.0, 20.0, "mm"),
    "analysis.min_region_blocks": (1, 100, "blocks"), "analysis.min_gradient": (0.0, 255.0, "grey levels"),
    "analysis.flat_tolerance": (1.0, 10.0, ""), "analysis.presmooth_px": (0.0, 5.0, "px"),
    "analysis.grow_threshold": (0.0, 1.0, ""), "analysis.grow_margin_mm": (0.0, 50.0, "mm"),
    "analysis.register_mm": (0.0, 5.0, "mm"),
    # the pause policy: every rule stays reachable, whatever is saved
    "policy.pause_ratio": (0.001, 0.5, "(a%)"), "policy.min_area_mm2": (0.0, 400.0, "mm^2"),
    "policy.consecutive_layers": (1, 10, "layers"), "policy.strong_outside_area_mm2": (1.0, 2500.0, "mm^2"),
    "policy.growth_ratio": (1.0, 10.0, ""), "policy.skip_first_layers": (0, 20, "layers"),
    "policy.growth_min_area_mm2": (0.0, 2500.0, "mm^2"), "policy.outside_pause_mm2": (0.0, 2500.0, "mm^2"),
    "policy.resume_grace_layers": (0, 20, "layers"),
    # per failure kind: its own thresholds stay below the whole observed square's worth of plastic
    **{f"policy.kinds.{k}.{t}": (0.0, 2500.0, "mm^2") for k in FAILURE_KINDS for t in ("warn_mm2", "act_mm2")},
    "scene.working_px": (160, 4096, "px"), "scene.margin_mm": (0.0, 20.0, "mm"), "scene.block_px": (2, 64, "px"),
    "scene.noise_k": (0.1, 100.0, ""), "scene.min_change": (0.0, 255.0, "grey levels"),
    "scene.min_region_mm2": (0.0, 2500.0, "mm^2"), "scene.max_changed_share": (0.01, 1.0, ""),
    "scene.shadow_reach": (0.0, 20.0, "heights"),
    "notify.min_interval_s": (0.0, 86400.0, "s"),
    "bed_check.min_area_mm2": (0.0, 2500.0, "mm^2"), "bed_check.block_px": (2, 64, "px"),
    "bed_check.noise_k": (0.1, 100.0, ""), "bed_check.min_change": (0.0, 255.0, "grey levels"),
    "bed_check.max_changed_share": (0.01, 1.0, ""),
    "first_layer.min_coverage": (0.0, 1.0, ""), "first_layer.max_missing_mm2": (0.0, 2500.0, "mm^2"),
    "first_layer.margin_mm": (0.0, 10.0, "mm"), "first_layer.min_change": (0.0, 255.0, "grey levels"),
    "extrusion.min_similarity": (0.0, 1.0, "(NCC)"), "extrusion.min_area_mm2": (0.0, 2500.0, "mm^2"),
    "extrusion.margin_mm": (0.0, 10.0, "mm"), "extrusion.block_px": (2, 64, "px"),
    "extrusion.working_px": (160, 4096, "px"), "extrusion.still_similarity": (0.0, 1.0, "(NCC)"),
    "extrusion.sure_similarity": (0.0, 1.0, "(NCC)"),
    "extrusion.still_share": (0.0, 1.0, ""),
    "layer_change.min_area_mm2": (0.0, 2500.0, "mm^2"), "layer_change.min_ncc": (0.0, 1.0, "(NCC)"),
    "layer_change.min_gain": (0.0, 2.0, "(NCC)"), "layer_change.min_parallax_change": (0.0, 2.0, "(1 - NCC)"),
    "layer_change.twin_tolerance": (0.0, 0.99, ""), "layer_change.wall_run_mm": (0.0, 100.0, "mm"),
    "layer_change.wall_min_ncc": (0.0, 1.0, "(NCC)"), "layer_change.wall_min_gain": (0.0, 2.0, "(NCC)"),
    "layer_change.min_snr": (0.0, 100.0, ""), "layer_change.window_px": (0.5, 16.0, "px"),
    "layer_change.block_px": (2, 64, "px"),
}
STOP_KEYS = ("action", "strong_action")  # policy keys whose "notify" means: never pause


class SettingsRejected(ConfigError):
    """Settings the dashboard refuses to store; the message is one line naming the key and the fix."""


def _range_text(key: str) -> str:
    lo, hi, unit = RANGES[key]
    return f"{lo:g} to {hi:g}{' ' + unit if unit else ''}"


def _range_key(path: tuple) -> str:
    """``("printer", "volume_max_mm", 1)`` -> ``"printer.volume_max_mm"`` (list indices dropped)."""
    return ".".join(str(p) for p in path if not isinstance(p, int))


def _numbers(value: Any, path: tuple = ()) -> list[tuple[tuple, float]]:
    """Every number (not bool) in a JSON-like tree with its path."""
    if isinstance(value, dict):
        return [n for k, v in value.items() for n in _numbers(v, (*path, k))]
    if isinstance(value, list | tuple):
        return [n for i, v in enumerate(value) for n in _numbers(v, (*path, i))]
    if isinstance(value, int | float) and not isinstance(value, bool):
        return [(path, float(value))]
    return []


def _reject(key: str, why: str) -> SettingsRejected:
    hint = f" (allowed: {_range_text(key)})" if key in RANGES else ""
    return SettingsRejected(" ".join(f"invalid setting {key or 'settings'}: {why}{hint}; fix it and save again.".split()))


def validation_line(exc: ValidationError) -> str:
    """One line from a pydantic error: the first bad key, why, its documented range, how many more."""
    errs = exc.errors()
    loc = errs[0]["loc"]
    key = _range_key(loc) if _range_key(loc) in RANGES else ".".join(str(p) for p in loc)
    more = f" (and {len(errs) - 1} more)" if len(errs) > 1 else ""
    return str(_reject(key, f"{errs[0]['msg']}{more}"))


def pausing_on(cfg: JobConfig) -> bool:
    """True when some pause rule may stop the print (``action`` or ``strong_action`` is not ``"notify"``)."""
    return any(getattr(cfg.policy, k) != "notify" for k in STOP_KEYS)


def validate_settings(data: dict[str, Any], current: JobConfig) -> JobConfig:
    """``data`` as a :class:`JobConfig` the dashboard may store.

    Parameters
    ----------
    data : dict
        The complete settings (JSON), after merging the request into the current ones.
    current : JobConfig
        The settings in force; a stopping ``policy.action``/``strong_action``
        may not become ``"notify"`` here (that is :func:`set_pausing`'s job).

    Raises
    ------
    SettingsRejected
        A number that is not finite or outside :data:`RANGES`, a value the
        config section refuses, or pausing switched off through the settings.
    """
    for path, x in _numbers(data):
        if not math.isfinite(x):
            raise _reject(_range_key(path), f"{x} is not a finite number")
    try:
        cfg = JobConfig.model_validate(data)
    except ValidationError as exc:
        raise SettingsRejected(validation_line(exc)) from None
    for path, x in _numbers(cfg.model_dump(mode="json")):
        key = _range_key(path)
        if key in RANGES and not RANGES[key][0] <= x <= RANGES[key][1]:
            raise _reject(key, f"{x:g} is out of range")
    for k in STOP_KEYS:
        if getattr(cfg.policy, k) == "notify" != getattr(current.policy, k):
            raise SettingsRejected(f"invalid setting policy.{k}: pausing is switched off only with the dashboard's "
                                   "pause switch (PUT /api/pausing); choose pause or cancel here.")
    for kind in FAILURE_KINDS:  # a failure kind silenced from the dashboard would silence the policy piece by piece
        if cfg.policy.kinds.of(kind).action == "notify" != current.policy.kinds.of(kind).action:
            raise SettingsRejected(f"invalid setting policy.kinds.{kind}.action: the dashboard does not turn a failure "
                                   "kind's stop into a notification; raise its act_mm2 instead, or set it in the job file.")
    return cfg


def set_pausing(cfg: JobConfig, enabled: bool) -> JobConfig:
    """``cfg`` with pausing switched off (both actions ``"notify"``) or on (``"notify"`` ones become ``"pause"``)."""
    update = {k: "pause" for k in STOP_KEYS if getattr(cfg.policy, k) == "notify"} if enabled else \
        {k: "notify" for k in STOP_KEYS}
    policy = cfg.policy.model_copy(update=update)
    return cfg.model_copy(update={"policy": policy})
