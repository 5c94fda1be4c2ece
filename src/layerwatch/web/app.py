"""The dashboard: a FastAPI app over a :class:`~layerwatch.storage.history.History`.

JSON API under ``/api`` (documented at ``/docs`` and ``/openapi.json``), an
HTML page at ``/`` (vanilla JS/CSS from ``web/static``), live updates by
server-sent events at ``/api/stream``. When a token is given every route but
``/login`` checks it (``Authorization: Bearer <token>`` or the cookie set by
``GET /login?token=...``) with a constant-time comparison.

Settings edited in the dashboard (``PUT``/``PATCH /api/settings``) are
validated by the same pydantic sections as the TOML job config and stored in
the history database (table ``settings``, name :data:`SETTINGS_KEY`), so they
survive a restart of the server and every dashboard on that database sees
them; a hand-written TOML file is never rewritten.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hmac
import json
import logging
from pathlib import Path
from typing import Any

from layerwatch.errors import LayerwatchError, StorageError, require
from layerwatch.pipeline.config import JobConfig
from layerwatch.storage.history import History

__all__ = ["create_app", "MAX_BODY", "COOKIE", "ACTIONS", "SETTINGS_KEY"]

log = logging.getLogger("layerwatch.web")

MAX_BODY = 1 << 20
COOKIE = "layerwatch_token"
ACTIONS = ("pause", "resume", "cancel", "acknowledge")
STATIC = Path(__file__).parent / "static"
SETTINGS_KEY = "job_config"


_SECRET = ("key", "token", "password", "secret")


def _hide_url(url: Any) -> Any:
    """``"tgram://bot/chat"`` -> ``"tgram://***"``: notification URLs carry tokens in host and path."""
    return f"{url.split('://', 1)[0]}://***" if isinstance(url, str) and "://" in url else url


def _redact(value: Any) -> Any:
    """Replace values of secret-looking keys (API keys, tokens, notification URLs) with ``"***"``."""
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            key = str(k).lower()
            if any(s in key for s in _SECRET) and v:
                out[k] = "***"
            elif key.endswith("_url") or key.endswith("_urls"):
                out[k] = [_hide_url(u) for u in v] if isinstance(v, list) else _hide_url(v)
            else:
                out[k] = _redact(v)
        return out
    if isinstance(value, list):
        return [_redact(v) for v in value]
    return value


def _keep_secrets(new: Any, current: Any) -> Any:
    """``new`` where a value is exactly what :func:`_redact` showed of ``current``'s replaced by ``current``'s.

    The page sends back the settings it was shown; a secret it never saw must not become ``"***"``.
    """
    if isinstance(new, dict) and isinstance(current, dict):
        shown = _redact(current)
        return {k: (current[k] if k in current and v == shown[k] and v != current[k]
                    else _keep_secrets(v, current.get(k))) for k, v in new.items()}
    return new


def _validation_line(exc: Any) -> str:
    """One line from a pydantic ``ValidationError``: the first bad key, why, and how many more."""
    errs = exc.errors()
    first = errs[0]
    where = ".".join(str(p) for p in first["loc"]) or "settings"
    more = f" (and {len(errs) - 1} more)" if len(errs) > 1 else ""
    return " ".join(f"invalid setting {where}: {first['msg']}{more}; fix it and save again.".split())


def _merge(base: dict[str, Any], patch: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``patch`` merged in, nested dicts merged key by key."""
    out = dict(base)
    for k, v in patch.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _jsonable(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if hasattr(value, "model_dump"):
        value = value.model_dump(mode="json")
    try:
        return _redact(json.loads(json.dumps(value, default=str)))
    except (TypeError, ValueError):
        return str(value)


def create_app(
    history: History,
    printers: dict[str, Any] | None = None,
    token: str | None = None,
    image_root: Path | None = None,
    settings: JobConfig | None = None,
    poll_s: float = 1.0,
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
        Access token; ``None`` disables authentication (loopback use only).
    image_root : Path, optional
        Folder whose files ``/api/image/{path}`` may serve; nothing else is served.
    settings : JobConfig, optional
        Job settings shown by ``/api/settings`` until someone saves settings
        in the dashboard (those are stored in ``history`` and win from then on);
        default: the evaluation's recommended settings, as the monitor uses them.
    poll_s : float
        Database poll interval of the live-update stream, s.
    """
    require("fastapi", "web", "The dashboard")
    from fastapi import Body, FastAPI, HTTPException, Query, Request
    from fastapi.responses import FileResponse, JSONResponse, RedirectResponse, StreamingResponse
    from fastapi.staticfiles import StaticFiles

    printers = dict(printers or {})
    root = Path(image_root).resolve() if image_root is not None else None
    if settings is None:  # what the monitor would run with: the evaluation's recommended settings
        from layerwatch.pipeline.config import recommended_config

        settings = recommended_config()
    fallback = settings
    app = FastAPI(title="layerwatch", version="1", description="Layer-by-layer print monitoring dashboard.")

    def authorised(request: Request) -> bool:
        if token is None:
            return True
        given = request.headers.get("authorization", "")
        candidate = given[7:] if given.lower().startswith("bearer ") else request.cookies.get(COOKIE, "")
        return hmac.compare_digest(candidate.encode(), token.encode())

    @app.middleware("http")
    async def guard(request: Request, call_next):
        length = request.headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > MAX_BODY):
            return JSONResponse({"detail": "request body larger than 1 MB"}, status_code=413)
        open_paths = ("/login",)
        if request.url.path not in open_paths and not authorised(request):
            return JSONResponse({"detail": "missing or wrong token; open /login?token=..."}, status_code=401)
        return await call_next(request)

    @app.exception_handler(StorageError)
    async def storage_failed(request: Request, exc: StorageError):
        return JSONResponse({"detail": str(exc)}, status_code=503)

    @app.exception_handler(LayerwatchError)
    async def lw_failed(request: Request, exc: LayerwatchError):
        return JSONResponse({"detail": str(exc)}, status_code=400)

    def need_job(job_id: int) -> dict[str, Any]:
        job = history.job(job_id)
        if job is None:
            raise HTTPException(404, f"no job {job_id}")
        return job

    @app.get("/login", include_in_schema=False)
    def login(token_: str = Query("", alias="token")):
        if token is not None and not hmac.compare_digest(token_.encode(), token.encode()):
            return JSONResponse({"detail": "wrong token"}, status_code=401)
        resp = RedirectResponse("/", status_code=303)
        if token is not None:
            resp.set_cookie(COOKIE, token, httponly=True, samesite="strict")
        return resp

    page = (STATIC / "index.html").read_text(encoding="utf-8")

    @app.get("/", include_in_schema=False)
    def index():
        from fastapi.responses import HTMLResponse

        try:  # the newest job's id lets the page fetch its rows together with the job list
            newest = history.last_job_id()
        except StorageError:
            newest = None  # the page shows the API's 503 itself
        html = page if newest is None else page.replace("<body>", f'<body data-newest="{int(newest)}">', 1)
        return HTMLResponse(html)

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/api/jobs", summary="All jobs, newest first")
    def jobs() -> list[dict[str, Any]]:
        return history.jobs()

    @app.get("/api/jobs/{job_id}", summary="One job with its settings")
    def job(job_id: int) -> dict[str, Any]:
        return need_job(job_id)

    @app.get("/api/jobs/{job_id}/layers", summary="Layer results of a job")
    def layers(job_id: int, full: bool = False) -> list[dict[str, Any]]:
        need_job(job_id)
        if full:
            return [r.to_dict() for r in history.layers(job_id)]
        return history.layer_summary(job_id)

    @app.get("/api/jobs/{job_id}/latest", summary="The newest layer result of a job (or null)")
    def latest(job_id: int) -> dict[str, Any] | None:
        need_job(job_id)
        res = history.latest_layer(job_id)
        return None if res is None else res.to_dict()

    @app.get("/api/jobs/{job_id}/events", summary="Event log of a job")
    def events(job_id: int, after: int = 0) -> list[dict[str, Any]]:
        need_job(job_id)
        return history.events(job_id, after=after)

    @app.get("/api/printers", summary="Known printers and their state")
    def printer_list() -> list[dict[str, Any]]:
        out = []
        for name, p in printers.items():
            try:
                status = _jsonable(p.status())
            except Exception as exc:  # a host that does not answer must not break the page
                status = {"error": str(exc)}
            out.append({"name": name, "status": status})
        return out

    def live_job(printer: str) -> int | None:
        """Newest job of ``printer`` that has not ended, or None."""
        return next((j["id"] for j in history.jobs() if j["printer"] == printer and j["outcome"] is None), None)

    @app.post("/api/jobs/{job_id}/acknowledge",
              summary="Accept the job's current failing regions",
              description="Records an `acknowledge` event; the monitor watching this job (same history database) "
                          "makes its pause policy accept the regions it sees now: they pause again only if they grow.")
    def acknowledge_job(job_id: int) -> dict[str, Any]:
        job = need_job(job_id)
        if job["outcome"] is not None:
            raise HTTPException(409, f"job {job_id} has ended ({job['outcome']}); only a running job can be acknowledged")
        eid = history.add_event(job_id, "acknowledge", "acknowledge requested from the dashboard", {"source": "dashboard"})
        return {"job_id": job_id, "event_id": eid}

    @app.post("/api/printers/{name}/{action}", summary="pause / resume / cancel / acknowledge")
    def printer_action(name: str, action: str, job_id: int | None = None) -> dict[str, Any]:
        """Call the printer connector; the action is logged on ``job_id`` (acknowledge: default the printer's running job)."""
        if name not in printers:
            raise HTTPException(404, f"no printer {name!r}")
        if action not in ACTIONS:
            raise HTTPException(404, f"unknown action {action!r}; use one of {', '.join(ACTIONS)}")
        p = printers[name]
        fn = getattr(p, action, None)
        if fn is not None:
            fn()
        elif action != "acknowledge":
            raise HTTPException(501, f"printer {name!r} cannot {action}")
        if job_id is None and action == "acknowledge":
            job_id = live_job(name)  # the monitor of that job reads the event and acknowledges its policy
        if job_id is not None and history.job(job_id) is not None:
            history.add_event(job_id, action, f"{action} requested from the dashboard", {"printer": name})
        try:
            status = _jsonable(p.status())
        except Exception as exc:
            status = {"error": str(exc)}
        return {"printer": name, "action": action, "status": status}

    @app.get("/api/metrics", summary="Names of the similarity measures")
    def metrics() -> list[str]:
        from layerwatch.analysis.settings import METRIC_NAMES

        return list(METRIC_NAMES)

    def current_settings() -> JobConfig:
        """The settings saved in the history (read each time: other dashboards may save too), else ``fallback``."""
        from pydantic import ValidationError

        stored = history.setting(SETTINGS_KEY)
        if stored is None:
            return fallback
        try:
            return JobConfig.model_validate(stored)
        except ValidationError as exc:  # saved by another layerwatch version: show the defaults, keep the row
            log.warning("saved dashboard settings are no longer valid (%s); showing defaults until saved again",
                        _validation_line(exc))
            return fallback

    def save_settings(data: dict[str, Any]) -> dict[str, Any]:
        from pydantic import ValidationError

        try:
            cfg = JobConfig.model_validate(_keep_secrets(data, current_settings().model_dump(mode="json")))
        except ValidationError as exc:
            raise HTTPException(422, _validation_line(exc)) from None
        history.set_setting(SETTINGS_KEY, cfg)
        return _redact(cfg.model_dump(mode="json"))

    @app.get("/api/settings", summary="Current job settings")
    def get_settings() -> dict[str, Any]:
        return _redact(current_settings().model_dump(mode="json"))

    @app.put("/api/settings", summary="Replace job settings (validated, saved in the history database); "
             "keys left out take the unsaved defaults (the recommended settings)")
    def put_settings(body: dict[str, Any] = Body(...)) -> dict[str, Any]:  # noqa: B008
        return save_settings(_merge(fallback.model_dump(mode="json"), body))

    @app.patch("/api/settings", summary="Change some settings, e.g. {\"policy\": {\"pause_ratio\": 0.2}} (validated, saved)")
    def patch_settings(body: dict[str, Any] = Body(...)) -> dict[str, Any]:  # noqa: B008
        return save_settings(_merge(current_settings().model_dump(mode="json"), body))

    @app.get("/api/image/{path:path}", summary="A stored picture under the image folder")
    def image(path: str):
        if root is None:
            raise HTTPException(404, "no image folder configured")
        try:
            target = (root / path).resolve()
        except (OSError, ValueError):
            raise HTTPException(404, "not found") from None
        if not target.is_relative_to(root) or not target.is_file():
            raise HTTPException(404, "not found")
        return FileResponse(target)

    @app.get("/api/stream", summary="Server-sent events: 'change' whenever the history changes")
    async def stream(limit: int = Query(3600, ge=1, le=86400)):
        async def gen():
            last = None
            for _ in range(limit):  # bounded: the browser's EventSource reconnects
                try:
                    rev = await asyncio.to_thread(history.revision)
                except StorageError as exc:
                    yield f"event: error\ndata: {json.dumps(str(exc))}\n\n"
                    return
                if rev != last:
                    last = rev
                    yield f"event: change\ndata: {json.dumps(list(rev))}\n\n"
                await asyncio.sleep(poll_s)

        return StreamingResponse(gen(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})

    return app
