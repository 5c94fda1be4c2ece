"""Settings routes: read, replace, change, their documented ranges, and the pause switch.

Saved settings live in the history database (table ``settings``, name
:data:`~layerwatch.web.context.SETTINGS_KEY`) so they survive a restart and
every dashboard on that database sees them; a hand-written TOML file is never
rewritten. Every change is checked by
:func:`layerwatch.web.settings.validate_settings` and written to the audit log.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, HTTPException, Request
from pydantic import BaseModel

from layerwatch.analysis.settings import METRIC_NAMES
from layerwatch.web import settings as checks
from layerwatch.web.context import SETTINGS_KEY, Ctx, Dashboard, audit
from layerwatch.web.redact import keep_secrets

__all__ = ["router"]

router = APIRouter(prefix="/api")


class Pausing(BaseModel):
    """The pause switch: ``false`` makes every pause rule only notify."""

    enabled: bool


def _merge(base: dict[str, Any], patch: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``patch`` merged in, nested dicts merged key by key."""
    out = dict(base)
    for k, v in patch.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _changes(old: Any, new: Any, path: str = "") -> dict[str, Any]:
    """Dotted keys whose value differs between two JSON trees, with the new value."""
    if isinstance(old, dict) and isinstance(new, dict):
        return {k: v for key in new for k, v in _changes(old.get(key), new[key], f"{path}{key}.").items()}
    return {} if old == new else {path.rstrip("."): new}


def _save(ctx: Dashboard, request: Request, data: dict[str, Any]) -> dict[str, Any]:
    current = ctx.settings()
    shown = current.model_dump(mode="json")
    try:
        cfg = checks.validate_settings(keep_secrets(data, shown), current)
    except checks.SettingsRejected as exc:
        raise HTTPException(422, str(exc)) from None
    ctx.history.set_setting(SETTINGS_KEY, cfg)
    audit(ctx, request, "settings", None, _changes(shown, cfg.model_dump(mode="json")))
    return cfg.model_dump(mode="json")


@router.get("/settings", summary="Current job settings (secrets redacted)")
def get_settings(ctx: Ctx) -> dict[str, Any]:
    return ctx.settings().model_dump(mode="json")


@router.put("/settings", summary="Replace job settings (validated, saved in the history database); "
            "keys left out take the unsaved defaults (the recommended settings)")
def put_settings(ctx: Ctx, request: Request, body: dict[str, Any] = Body(...)) -> dict[str, Any]:  # noqa: B008
    return _save(ctx, request, _merge(ctx.fallback.model_dump(mode="json"), body))


@router.patch("/settings", summary="Change some settings, e.g. {\"policy\": {\"pause_ratio\": 0.2}} (validated, saved)")
def patch_settings(ctx: Ctx, request: Request, body: dict[str, Any] = Body(...)) -> dict[str, Any]:  # noqa: B008
    return _save(ctx, request, _merge(ctx.settings().model_dump(mode="json"), body))


@router.get("/settings/ranges", summary="The range the dashboard accepts for each numeric setting",
            description="`{\"policy.pause_ratio\": {\"min\": 0.001, \"max\": 0.5, \"unit\": \"(a%)\"}, ...}`")
def ranges() -> dict[str, dict[str, Any]]:
    return {k: {"min": lo, "max": hi, "unit": unit} for k, (lo, hi, unit) in checks.RANGES.items()}


@router.get("/pausing", summary="Whether a failure may pause the print (the pause switch)")
def get_pausing(ctx: Ctx) -> dict[str, bool]:
    return {"enabled": checks.pausing_on(ctx.settings())}


@router.put("/pausing", summary="The pause switch: {\"enabled\": false} makes every rule only notify",
            description="The only way to stop layerwatch from pausing a print; the dashboard shows it, "
                        "and the audit log records who switched it.")
def put_pausing(ctx: Ctx, request: Request, body: Pausing) -> dict[str, bool]:
    cfg = checks.set_pausing(ctx.settings(), body.enabled)
    ctx.history.set_setting(SETTINGS_KEY, cfg)
    audit(ctx, request, "pausing on" if body.enabled else "pausing off")
    return {"enabled": checks.pausing_on(cfg)}


@router.get("/metrics", summary="Names of the similarity measures")
def metrics() -> list[str]:
    return list(METRIC_NAMES)


