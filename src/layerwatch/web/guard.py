"""The dashboard's door: one ASGI middleware in front of every route.

In order, for each HTTP request:

1. **Host allow-list** (DNS rebinding): the ``Host`` header must name an
   allowed host (default without a token: ``127.0.0.1``, ``localhost``,
   ``[::1]``), else 421.
2. **Body size** declared by ``Content-Length`` above :data:`MAX_BODY` -> 413
   at once; bodies without a length (chunked) are counted while they stream
   and cut at the same size (the route sees a 413 after at most
   :data:`MAX_BODY` bytes were buffered).
3. **Token** (when one is set): ``Authorization: Bearer`` or a logged-in
   session cookie; a wrong bearer token counts towards the client's
   throttle, and a blocked client gets 429 with ``Retry-After``.
4. **Cross-site checks** on every state-changing method (``POST``, ``PUT``,
   ``PATCH``, ``DELETE``) in every mode: ``Sec-Fetch-Site`` must be
   ``same-origin`` or ``none``, ``Origin`` (if sent) must be this host, and
   the ``X-CSRF-Token`` header must be the session's CSRF token (requests
   authenticated by a bearer token are exempt: browsers never add that
   header by themselves).
5. **Headers** on every response: Content-Security-Policy with
   ``frame-ancestors 'none'``, ``X-Content-Type-Options: nosniff``,
   ``X-Frame-Options: DENY``, ``Referrer-Policy: no-referrer``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.requests import HTTPConnection
from starlette.responses import JSONResponse, RedirectResponse, Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from layerwatch.web.sessions import CSRF_HEADER, SESSION_COOKIE, Session, Sessions, Throttle
from layerwatch.web.settings import MAX_BODY
from layerwatch.web.token import same_token

__all__ = ["Guard", "Door", "PAGE_CSP", "UNSAFE_METHODS", "client_of", "host_name"]

UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
PAGE_CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
            "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
# Swagger UI / ReDoc (FastAPI's /docs, /redoc) load from a CDN and use an inline script
DOCS_CSP = ("default-src 'self'; script-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net; "
            "style-src 'self' https://cdn.jsdelivr.net; img-src 'self' data: https://fastapi.tiangolo.com; "
            "object-src 'none'; base-uri 'none'; frame-ancestors 'none'")
OPEN_PATHS = frozenset({"/login"})  # reachable without the token (the login form itself)
_HEADERS = [(b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"DENY"),
            (b"referrer-policy", b"no-referrer"), (b"cross-origin-opener-policy", b"same-origin")]


@dataclass
class Door:
    """What the guard checks against (one per app).

    Parameters
    ----------
    token : str or None
        Access token; ``None``: no login (loopback use).
    allowed_hosts : frozenset of str or None
        Host names (lower case, without port) the ``Host`` header may carry;
        ``None``: any (only when a token is set).
    sessions, throttle
        Session signer and wrong-token throttle.
    """

    token: str | None
    allowed_hosts: frozenset[str] | None
    sessions: Sessions = field(default_factory=Sessions)
    throttle: Throttle = field(default_factory=Throttle)


def client_of(scope: Scope) -> str:
    """The client's address as the server saw it (``"unknown"`` when the server does not say)."""
    client = scope.get("client")
    return str(client[0]) if client else "unknown"


def host_name(host: str) -> str:
    """``"LocalHost:8765"`` -> ``"localhost"``; ``"[::1]:8765"`` -> ``"[::1]"``."""
    host = host.strip().lower()
    if host.startswith("["):
        return host.split("]", 1)[0] + "]"
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def _refuse(status: int, detail: str, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)


def _cross_site(headers: Headers) -> str | None:
    """Why a state-changing request is cross-site, or ``None``."""
    site = headers.get("sec-fetch-site")
    if site is not None and site not in ("same-origin", "none"):
        return f"cross-site request refused (Sec-Fetch-Site: {site})"
    origin = headers.get("origin")
    if origin is not None:
        netloc = urlsplit(origin).netloc.lower() if "://" in origin else ""
        if not netloc or netloc != headers.get("host", "").lower():
            return "cross-origin request refused (Origin is not this dashboard)"
    return None


class Guard:
    """ASGI middleware enforcing :class:`Door` (see the module docstring for the checks)."""

    def __init__(self, app: ASGIApp, door: Door) -> None:
        self.app, self.door = app, door

    def _authenticate(self, conn: HTTPConnection, scope: Scope) -> Response | None:
        """Set ``scope["state"]`` ``session``/``auth``; a refusal when the token is needed and missing."""
        door = self.door
        session = door.sessions.verify(conn.cookies.get(SESSION_COOKIE))
        state = scope.setdefault("state", {})
        state["session"], state["auth"] = session, "none"
        if door.token is None:
            return None
        given = conn.headers.get("authorization", "")
        if given[:7].lower() == "bearer ":
            client = client_of(scope)
            wait = door.throttle.retry_after(client)
            if wait:
                return _refuse(429, f"too many wrong tokens; try again in {wait} s", {"Retry-After": str(wait)})
            if same_token(given[7:].strip(), door.token):
                state["auth"] = "bearer"
                return None
            door.throttle.fail(client)
            return _refuse(401, "wrong token; use the one in the .token file beside the history database")
        if session is not None and session.authenticated:
            state["auth"] = "session"
            return None
        if scope["path"] in OPEN_PATHS:
            return None
        if scope["path"] == "/" and scope["method"] == "GET":
            return RedirectResponse("/login", status_code=303)
        return _refuse(401, "missing or wrong token; log in at /login")

    def _check(self, scope: Scope) -> Response | None:
        conn = HTTPConnection(scope)
        door = self.door
        if door.allowed_hosts is not None and host_name(conn.headers.get("host", "")) not in door.allowed_hosts:
            return _refuse(421, "this dashboard does not answer to that Host name; open it by an allowed name "
                                "(loopback: http://127.0.0.1:PORT/) or add the name with --allowed-host")
        length = conn.headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > MAX_BODY):
            return _refuse(413, f"request body larger than {MAX_BODY >> 20} MiB", {"Connection": "close"})
        refusal = self._authenticate(conn, scope)
        if refusal is not None or scope["method"] not in UNSAFE_METHODS:
            return refusal
        why = _cross_site(conn.headers)
        if why:
            return _refuse(403, why)
        state = scope["state"]
        if state["auth"] != "bearer" and scope["path"] not in OPEN_PATHS:
            session: Session | None = state["session"]
            if not door.sessions.csrf_ok(session, conn.headers.get(CSRF_HEADER)):
                return _refuse(403, "missing or wrong CSRF token; reload the dashboard page (scripts: GET "
                                    "/api/session, then send its csrf value as X-CSRF-Token with its cookie)")
        return None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        csp = (DOCS_CSP if scope["path"] in ("/docs", "/redoc") else PAGE_CSP).encode()
        started = False

        async def send_with_headers(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                message["headers"] = [*message.get("headers", []), *_HEADERS, (b"content-security-policy", csp)]
            await send(message)

        refusal = self._check(scope)
        if refusal is not None:
            await refusal(scope, receive, send_with_headers)
            return
        received = 0

        async def capped_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > MAX_BODY:  # FastAPI re-raises HTTPException from body reading: a 413
                    raise HTTPException(413, f"request body larger than {MAX_BODY >> 20} MiB",
                                        headers={"Connection": "close"})
            return message

        try:
            await self.app(scope, capped_receive, send_with_headers)
        except HTTPException as exc:  # raised where no FastAPI handler turned it into a response
            if started or exc.status_code != 413:
                raise
            await _refuse(413, str(exc.detail), {"Connection": "close"})(scope, receive, send_with_headers)
