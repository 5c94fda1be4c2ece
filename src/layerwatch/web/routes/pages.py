"""HTML pages and sessions: ``/``, ``/login``, ``/logout``, ``/api/session``.

Every visitor of a page gets a session (signed cookie, HttpOnly,
SameSite=Strict, expiring, Secure over TLS); the page carries the session's
CSRF token in ``<meta name="csrf-token">``. With a token, ``/login`` takes it
once (form field, or ``?token=`` from the link ``layerwatch serve`` prints,
answered by a redirect so it leaves the address bar) and replaces the
session by a logged-in one: the token is not needed in any URL after that.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

from fastapi import APIRouter, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response

from layerwatch.errors import StorageError
from layerwatch.web.context import Ctx, Dashboard, audit
from layerwatch.web.guard import client_of
from layerwatch.web.sessions import SESSION_COOKIE, Session
from layerwatch.web.token import same_token

__all__ = ["router", "STATIC"]

STATIC = Path(__file__).resolve().parents[1] / "static"
router = APIRouter()
_LOGIN = """<!doctype html><html lang="en"><head><meta charset="utf-8"><title>layerwatch login</title>
<meta name="viewport" content="width=device-width, initial-scale=1"></head><body>
<h1>layerwatch</h1><p>{message}</p>
<form method="post" action="/login"><input type="hidden" name="csrf" value="{csrf}">
<label>access token <input name="token" type="password" autocomplete="current-password" autofocus></label>
<button type="submit">Log in</button></form></body></html>"""


def _session(ctx: Dashboard, request: Request, authenticated: bool = False) -> tuple[Session, str | None]:
    """The request's valid session and ``None``, or a new one and its cookie value (always new at login)."""
    current = request.scope.get("state", {}).get("session")
    if current is not None and not authenticated:
        return current, None
    session, cookie = ctx.door.sessions.issue(authenticated)
    request.scope.setdefault("state", {})["session"] = session
    return session, cookie


def _with_cookie(ctx: Dashboard, request: Request, response: Response, cookie: str | None) -> Response:
    """``response`` setting the session cookie (HttpOnly, SameSite=Strict, expiring, Secure over TLS)."""
    if cookie is not None:
        response.set_cookie(SESSION_COOKIE, cookie, max_age=int(ctx.door.sessions.lifetime_s), path="/",
                            httponly=True, samesite="strict", secure=request.url.scheme == "https")
    return response


@router.get("/", include_in_schema=False)
def index(ctx: Ctx, request: Request) -> Response:
    page = (STATIC / "index.html").read_text(encoding="utf-8")
    try:  # the newest job's id lets the page fetch its rows together with the job list
        newest = ctx.history.last_job_id()
    except StorageError:
        newest = None  # the page shows the API's 503 itself
    if newest is not None:
        page = page.replace("<body>", f'<body data-newest="{int(newest)}">', 1)
    return _page(ctx, request, page)


@router.get("/farm", include_in_schema=False)
def farm(ctx: Ctx, request: Request) -> Response:
    """The farm view: a card per printer (state, job, layer, overlay, a% sparkline, alarm, buttons)."""
    return _page(ctx, request, (STATIC / "farm.html").read_text(encoding="utf-8"))


def _page(ctx: Dashboard, request: Request, page: str) -> Response:
    """``page`` with the session's CSRF token in its ``<meta name="csrf-token">`` (and the session cookie)."""
    session, cookie = _session(ctx, request)
    csrf = ctx.door.sessions.csrf(session)
    page = page.replace('<meta name="csrf-token" content="">', f'<meta name="csrf-token" content="{csrf}">', 1)
    return _with_cookie(ctx, request, HTMLResponse(page, headers={"Cache-Control": "no-store"}), cookie)


def _login_page(ctx: Dashboard, request: Request, message: str, status: int = 200) -> Response:
    session, cookie = _session(ctx, request)
    page = _LOGIN.format(message=html.escape(message), csrf=ctx.door.sessions.csrf(session))
    return _with_cookie(ctx, request, HTMLResponse(page, status_code=status, headers={"Cache-Control": "no-store"}),
                        cookie)


def _try_token(ctx: Dashboard, request: Request, given: str) -> Response | None:
    """A logged-in redirect to ``/`` for the right token; ``None`` for a wrong one (counted)."""
    client = client_of(request.scope)
    wait = ctx.door.throttle.retry_after(client)
    if wait:
        return JSONResponse({"detail": f"too many wrong tokens; try again in {wait} s"}, status_code=429,
                            headers={"Retry-After": str(wait)})
    if ctx.door.token is None or not same_token(given, ctx.door.token):
        ctx.door.throttle.fail(client)
        return None
    _, cookie = _session(ctx, request, authenticated=True)
    return _with_cookie(ctx, request, RedirectResponse("/", status_code=303), cookie)


@router.get("/login", include_in_schema=False)
def login_form(ctx: Ctx, request: Request, token: str = Query("", max_length=512)) -> Response:
    if ctx.door.token is None:
        return RedirectResponse("/", status_code=303)
    if not token:
        return _login_page(ctx, request, "Enter the access token printed by `layerwatch serve`.")
    return _try_token(ctx, request, token) or _login_page(ctx, request, "Wrong token.", 401)


@router.post("/login", include_in_schema=False)
async def login(ctx: Ctx, request: Request) -> Response:
    form = parse_qs((await request.body()).decode("utf-8", "replace"))
    csrf, token = form.get("csrf", [""])[0], form.get("token", [""])[0]
    if not ctx.door.sessions.csrf_ok(request.scope["state"].get("session"), csrf):
        return _login_page(ctx, request, "The form expired; enter the token again.", 403)
    if ctx.door.token is None:
        return RedirectResponse("/", status_code=303)
    return _try_token(ctx, request, token) or _login_page(ctx, request, "Wrong token.", 401)


@router.post("/logout", include_in_schema=False)
def logout(ctx: Ctx, request: Request) -> Response:
    audit(ctx, request, "logout")
    resp = RedirectResponse("/login" if ctx.door.token else "/", status_code=303)
    resp.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return resp


@router.get("/api/session", summary="This client's session and its CSRF token",
            description="Sets the session cookie when there is none. Send `csrf` as the `X-CSRF-Token` header "
                        "(with the cookie) on every POST/PUT/PATCH; scripts with a bearer token need neither.")
def session(ctx: Ctx, request: Request, response: Response) -> dict[str, Any]:
    s, cookie = _session(ctx, request)
    _with_cookie(ctx, request, response, cookie)
    return {"csrf": ctx.door.sessions.csrf(s), "expires": s.expires, "authenticated": s.authenticated,
            "token_required": ctx.door.token is not None}
