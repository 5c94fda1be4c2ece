"""Jobs, their layers and events, the job's acknowledge button, and the live-update stream."""

from __future__ import annotations

import asyncio
import json
from typing import Any

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import StreamingResponse

from layerwatch.errors import StorageError
from layerwatch.web.context import Ctx, audit

__all__ = ["router"]

router = APIRouter(prefix="/api")


@router.get("/jobs", summary="All jobs, newest first")
def jobs(ctx: Ctx) -> list[dict[str, Any]]:
    return ctx.history.jobs()


@router.get("/jobs/{job_id}", summary="One job with its settings (secrets redacted) and last layer")
def job(ctx: Ctx, job_id: int) -> dict[str, Any]:
    return ctx.need_job(job_id)


@router.get("/jobs/{job_id}/layers", summary="Layer results of a job")
def layers(ctx: Ctx, job_id: int, full: bool = False) -> list[dict[str, Any]]:
    ctx.need_job(job_id)
    if full:
        return [r.to_dict() for r in ctx.history.layers(job_id)]
    return ctx.history.layer_summary(job_id)


@router.get("/jobs/{job_id}/latest", summary="The newest layer result of a job (or null)")
def latest(ctx: Ctx, job_id: int) -> dict[str, Any] | None:
    ctx.need_job(job_id)
    res = ctx.history.latest_layer(job_id)
    return None if res is None else res.to_dict()


@router.get("/jobs/{job_id}/events", summary="Event log of a job")
def events(ctx: Ctx, job_id: int, after: int = 0) -> list[dict[str, Any]]:
    ctx.need_job(job_id)
    return ctx.history.events(job_id, after=after)


@router.post("/jobs/{job_id}/acknowledge",
             summary="Accept the job's current failing regions",
             description="Records an `acknowledge` event; the monitor watching this job (same history database) "
                         "makes its pause policy accept the regions it sees now: they pause again only if they grow.")
def acknowledge_job(ctx: Ctx, request: Request, job_id: int) -> dict[str, Any]:
    found = ctx.need_job(job_id)
    if found["outcome"] is not None:
        raise HTTPException(409, f"job {job_id} has ended ({found['outcome']}); only a running job can be acknowledged")
    eid = ctx.history.add_event(job_id, "acknowledge", "acknowledge requested from the dashboard", {"source": "dashboard"})
    audit(ctx, request, "acknowledge", f"job {job_id}")
    return {"job_id": job_id, "event_id": eid}


@router.get("/audit", summary="Audit log: who paused, resumed, cancelled, acknowledged or changed settings",
            description="Newest first; each entry has the time, action, target, client address and credential.")
def audit_log(ctx: Ctx, after: int = Query(0, ge=0), limit: int = Query(200, ge=1, le=1000)) -> list[dict[str, Any]]:
    return ctx.history.audit(after=after, limit=limit)


@router.get("/stream", summary="Server-sent events: 'change' whenever the history changes")
async def stream(ctx: Ctx, limit: int = Query(3600, ge=1, le=86400)) -> StreamingResponse:
    async def gen():
        last = None
        for _ in range(limit):  # bounded: the browser's EventSource reconnects
            try:
                rev = await asyncio.to_thread(ctx.history.revision)
            except StorageError as exc:
                yield f"event: error\ndata: {json.dumps(str(exc))}\n\n"
                return
            if rev != last:
                last = rev
                yield f"event: change\ndata: {json.dumps(list(rev))}\n\n"
            await asyncio.sleep(ctx.poll_s)

    return StreamingResponse(gen(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})
