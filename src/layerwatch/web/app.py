"""The dashboard: a FastAPI app over a :class:`~layerwatch.storage.history.History`, built from routers.

JSON API under ``/api`` (documented at ``/docs`` and ``/openapi.json``), an
HTML page at ``/`` (vanilla JS/CSS from ``web/static``), live updates by
server-sent events at ``/api/stream``. The routers
(:mod:`layerwatch.web.routes`) hold the routes; :mod:`layerwatch.web.guard`
checks Host, body size, token, cross-site requests and CSRF in front of all
of them; :mod:`layerwatch.web.redact` strips secrets from every JSON answer.
What is checked and why: ``docs/security.md``.

This module needs the optional ``web`` extra (FastAPI/Starlette); code that only needs the
settings key imports it from :mod:`layerwatch.web.settings`.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from layerwatch.pipeline.config import JobConfig, recommended_config
from layerwatch.storage.history import History
from layerwatch.web.context import Dashboard, add_error_handlers
from layerwatch.web.guard import Door, Guard
from layerwatch.web.redact import RedactedJSON
from layerwatch.web.routes import files, jobs, pages
from layerwatch.web.routes import printers as printer_routes
from layerwatch.web.routes import settings as settings_routes
from layerwatch.web.sessions import Sessions, Throttle
from layerwatch.web.settings import MAX_BODY, SETTINGS_KEY
from layerwatch.web.token import LOOPBACK_NAMES

__all__ = ["create_app", "MAX_BODY", "SETTINGS_KEY"]


def _private_files(history: History, token_file: Path | None) -> frozenset[Path]:
    """Resolved paths never served: the database, its WAL/SHM/journal, and the token file."""
    out = set()
    if history.path is not None:
        db = history.path.resolve()
        out |= {db, *(db.with_name(db.name + s) for s in ("-wal", "-shm", "-journal"))}
        out.add(db.with_suffix(".token"))
    if token_file is not None:
        out.add(Path(token_file).resolve())
    return frozenset(out)


def _host_name(host: str) -> str:
    """``"Printer.Local"`` -> ``"printer.local"``; IPv6 literals in brackets as the Host header has them."""
    host = host.strip().lower()
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


def _allowed(token: str | None, allowed_hosts: Iterable[str] | None) -> frozenset[str] | None:
    """The Host allow-list: loopback names plus ``allowed_hosts``; ``None`` (any) only with a token."""
    loopback = frozenset(_host_name(h) for h in LOOPBACK_NAMES)
    if allowed_hosts is None:
        return None if token is not None else loopback
    names = {_host_name(h) for h in allowed_hosts}
    return None if "*" in names and token is not None else loopback | (names - {"*"})


def create_app(
    history: History,
    printers: dict[str, Any] | None = None,
    token: str | None = None,
    image_root: Path | None = None,
    settings: JobConfig | None = None,
    poll_s: float = 1.0,
    allowed_hosts: Iterable[str] | None = None,
    token_file: Path | None = None,
    session_s: float = 12 * 3600,
):
    """Build the dashboard app.

    Parameters
    ----------
    history : History
        Database the pages and API read.
    printers : dict of str to Printer, optional
        Objects with ``pause()``, ``resume()``, ``cancel()`` and ``status()``
        (``acknowledge()`` optional), keyed by printer name.
    token : str, optional
        Access token; ``None`` disables login (loopback use only: the Host
        allow-list then admits loopback names only).
    image_root : Path, optional
        The artifacts folder: ``/api/image/{path}`` serves the layers' recorded
        pictures under it and nothing else (see :mod:`layerwatch.web.routes.files`).
    settings : JobConfig, optional
        Job settings shown by ``/api/settings`` until someone saves settings
        in the dashboard (those are stored in ``history`` and win from then on);
        default: the evaluation's recommended settings, as the monitor uses them.
    poll_s : float
        Database poll interval of the live-update stream, s.
    allowed_hosts : iterable of str, optional
        Host names (``Host`` header, port ignored) the dashboard answers to,
        besides ``127.0.0.1``, ``localhost`` and ``[::1]``; default: those
        only without a token, any with a token (``["*"]`` likewise).
    token_file : Path, optional
        Where the token is stored; never served.
    session_s : float
        Lifetime of a login session, s.
    """
    if settings is None:  # what the monitor would run with: the evaluation's recommended settings
        settings = recommended_config()
    door = Door(token, _allowed(token, allowed_hosts), Sessions(lifetime_s=session_s), Throttle())
    app = FastAPI(title="layerwatch", version="1", description="Layer-by-layer print monitoring dashboard.",
                  default_response_class=RedactedJSON)
    app.state.dashboard = Dashboard(
        history=history, printers=dict(printers or {}), fallback=settings,
        image_root=None if image_root is None else Path(image_root).resolve(),
        private=_private_files(history, token_file), door=door, poll_s=float(poll_s))
    add_error_handlers(app)
    for module in (pages, jobs, printer_routes, settings_routes, files):
        app.include_router(module.router)
    app.mount("/static", StaticFiles(directory=pages.STATIC), name="static")
    app.add_middleware(Guard, door=door)
    return app
