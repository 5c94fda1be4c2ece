"""Printers: their state, and the pause / resume / cancel / acknowledge buttons."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Request, Response

from layerwatch.web.context import Ctx, Dashboard, audit
from layerwatch.web.redact import jsonable

__all__ = ["router", "ACTIONS"]

ACTIONS = ("pause", "resume", "cancel", "acknowledge")
router = APIRouter(prefix="/api/printers")


def _status(printer: Any) -> Any:
    try:
        return jsonable(printer.status())
    except Exception as exc:  # a host that does not answer must not break the page
        return {"error": str(exc)}


def _live_job(ctx: Dashboard, printer: str) -> int | None:
    """Newest job of ``printer`` that has not ended, or None."""
    return next((j["id"] for j in ctx.history.jobs() if j["printer"] == printer and j["outcome"] is None), None)


def _card(name: str, printer: Any) -> dict[str, Any]:
    """One printer's row: a farm station's own card, else what its ``status()`` says."""
    summary = getattr(printer, "summary", None)
    if summary is not None:
        return {**jsonable(summary()), "name": name}
    st = _status(printer)
    if "error" in st:
        return {"name": name, "state": "error", "message": st["error"], "job": None, "layer": None,
                "ratio": None, "alarm": None, "status": st}
    return {"name": name, "state": st.get("state"), "message": None, "job": st.get("file"), "layer": st.get("layer"),
            "ratio": None, "alarm": None, "status": st}


@router.get("", summary="Known printers and their state",
            description="Each row: `name`, `state` (printing, paused, idle, error, ...), `message` (why, in error), "
                        "`job`, `layer`, `ratio` (last a%); farm printers add `job_id`, `layers`, `ratios` "
                        "(sparkline), `alarm` (last notify/pause: action, layer, reason), `dropped`, `late`, `thumb`.")
def printer_list(ctx: Ctx) -> list[dict[str, Any]]:
    return [_card(name, p) for name, p in ctx.printers.items()]


@router.get("/{name}/thumb.png", summary="Overlay thumbnail of the printer's last analysed layer (farm printers)",
            response_class=Response, responses={200: {"content": {"image/png": {}}}})
def printer_thumb(ctx: Ctx, name: str) -> Response:
    p = ctx.printers.get(name)
    thumb = getattr(p, "thumb", None) if p is not None else None
    if thumb is None:
        raise HTTPException(404, f"no overlay for printer {name!r} yet")
    return Response(thumb, media_type="image/png", headers={"Cache-Control": "no-store"})


@router.post("/{name}/{action}", summary="pause / resume / cancel / acknowledge")
def printer_action(ctx: Ctx, request: Request, name: str, action: str, job_id: int | None = None) -> dict[str, Any]:
    """Call the printer connector; the action is logged on ``job_id`` (acknowledge: default the printer's running job)."""
    if name not in ctx.printers:
        raise HTTPException(404, f"no printer {name!r}")
    if action not in ACTIONS:
        raise HTTPException(404, f"unknown action {action!r}; use one of {', '.join(ACTIONS)}")
    p = ctx.printers[name]
    fn = getattr(p, action, None)
    if fn is None and action != "acknowledge":
        raise HTTPException(501, f"printer {name!r} cannot {action}")
    audit(ctx, request, action, f"printer {name}", {"job_id": job_id})
    if fn is not None:
        fn()
    if job_id is None and action == "acknowledge":
        job_id = _live_job(ctx, name)  # the monitor of that job reads the event and acknowledges its policy
    if job_id is not None and ctx.history.job(job_id) is not None:
        ctx.history.add_event(job_id, action, f"{action} requested from the dashboard", {"printer": name})
    return {"printer": name, "action": action, "status": _status(p)}
