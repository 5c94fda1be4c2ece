"""What every dashboard route reads: the :class:`Dashboard` of its app, and the audit helper."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, FastAPI, HTTPException, Request
from pydantic import ValidationError

from layerwatch.errors import LayerwatchError, StorageError
from layerwatch.pipeline.config import JobConfig
from layerwatch.storage.history import History
from layerwatch.web.guard import Door, client_of
from layerwatch.web.redact import RedactedJSON, redact
from layerwatch.web.settings import SETTINGS_KEY, validation_line

__all__ = ["Dashboard", "Ctx", "audit", "add_error_handlers", "SETTINGS_KEY"]

log = logging.getLogger("layerwatch.web")


@dataclass
class Dashboard:
    """The state of one dashboard app.

    Parameters
    ----------
    history : History
        Database the pages and API read (and the audit log is written to).
    printers : dict of str to Printer
        Printer connectors keyed by name.
    fallback : JobConfig
        Settings shown until someone saves settings in the dashboard.
    image_root : Path or None
        Resolved artifacts folder; ``None``: no images are served.
    private : frozenset of Path
        Resolved files never served whatever the request (database, WAL, SHM, token).
    door : Door
        Token, allowed hosts, sessions and throttle (see :mod:`layerwatch.web.guard`).
    poll_s : float
        Database poll interval of the live-update stream, s.
    """

    history: History
    printers: dict[str, Any]
    fallback: JobConfig
    image_root: Path | None
    private: frozenset[Path]
    door: Door
    poll_s: float

    def need_job(self, job_id: int) -> dict[str, Any]:
        """The job ``job_id`` or a 404."""
        job = self.history.job(job_id)
        if job is None:
            raise HTTPException(404, f"no job {job_id}")
        return job

    def settings(self) -> JobConfig:
        """Settings saved in the history (read each time: other dashboards may save too), else ``fallback``."""
        stored = self.history.setting(SETTINGS_KEY)
        if stored is None:
            return self.fallback
        try:
            return JobConfig.model_validate(stored)
        except ValidationError as exc:  # saved by another layerwatch version: show the defaults, keep the row
            log.warning("saved dashboard settings are no longer valid (%s); showing defaults until saved again",
                        validation_line(exc))
            return self.fallback


def _dashboard(request: Request) -> Dashboard:
    return request.app.state.dashboard


Ctx = Annotated[Dashboard, Depends(_dashboard)]


def actor(request: Request) -> str:
    """Who is asking, for the audit log: the kind of credential and a short session id."""
    state = request.scope.get("state", {})
    session = state.get("session")
    sid = f" {session.sid[:8]}" if session is not None else ""
    return {"bearer": "token (Authorization header)", "session": f"token session{sid}"}.get(
        state.get("auth", "none"), f"local, no token (session{sid or ' none'})")


def audit(ctx: Dashboard, request: Request, action: str, target: str | None = None, detail: Any = None) -> int:
    """Record a state-changing dashboard action (redacted detail) in the history's audit log."""
    return ctx.history.add_audit(action, client_of(request.scope), actor(request), target,
                                 None if detail is None else redact(detail))


def add_error_handlers(app: FastAPI) -> None:
    """Storage failures answer 503, other :class:`LayerwatchError` 400, each with its one-line message."""

    @app.exception_handler(StorageError)
    async def storage_failed(request: Request, exc: StorageError) -> RedactedJSON:
        return RedactedJSON({"detail": str(exc)}, status_code=503)

    @app.exception_handler(LayerwatchError)
    async def lw_failed(request: Request, exc: LayerwatchError) -> RedactedJSON:
        return RedactedJSON({"detail": str(exc)}, status_code=400)
