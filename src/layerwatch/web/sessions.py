"""Browser sessions, CSRF tokens and the throttle on wrong tokens.

A session cookie is never the access token: it is ``SID.EXPIRY.AUTH.SIG``
where ``SIG`` is an HMAC-SHA256 (key: a random secret of this server
process) over the rest, ``EXPIRY`` a Unix time and ``AUTH`` ``1`` once the
token was shown at ``/login``. Every visitor of the page gets an
unauthenticated session (it carries the CSRF binding in the default
loopback mode without a token); logging in replaces it by a new one.

The CSRF token of a session is ``HMAC(secret, "csrf." + SID)``: the page
receives it in a ``<meta>`` tag (or from ``GET /api/session``) and sends it
as the ``X-CSRF-Token`` header of every state-changing request.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets
import time
from collections import OrderedDict, deque
from dataclasses import dataclass

__all__ = ["Session", "Sessions", "Throttle", "SESSION_COOKIE", "CSRF_HEADER"]

SESSION_COOKIE = "layerwatch_session"
CSRF_HEADER = "x-csrf-token"


@dataclass(frozen=True)
class Session:
    """A verified session: id, expiry (Unix s) and whether it logged in with the token."""

    sid: str
    expires: int
    authenticated: bool


def _b64(raw: bytes) -> str:
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode()


class Sessions:
    """Issues and verifies signed session cookies.

    Parameters
    ----------
    secret : bytes, optional
        HMAC key; default: 32 random bytes (sessions end when the server restarts).
    lifetime_s : float
        How long a session lasts, s (default 12 h).
    """

    def __init__(self, secret: bytes | None = None, lifetime_s: float = 12 * 3600) -> None:
        self._secret = secret or secrets.token_bytes(32)
        self.lifetime_s = float(lifetime_s)

    def _sign(self, text: str) -> str:
        return _b64(hmac.new(self._secret, text.encode(), hashlib.sha256).digest())

    def issue(self, authenticated: bool) -> tuple[Session, str]:
        """A new session and its cookie value."""
        s = Session(secrets.token_urlsafe(16), int(time.time() + self.lifetime_s), authenticated)
        body = f"{s.sid}.{s.expires}.{int(authenticated)}"
        return s, f"{body}.{self._sign(body)}"

    def verify(self, cookie: str | None) -> Session | None:
        """The session of a cookie value, or ``None`` when it is missing, forged or expired."""
        parts = (cookie or "").split(".")
        if len(parts) != 4 or not parts[1].isdigit() or parts[2] not in ("0", "1"):
            return None
        body = ".".join(parts[:3])
        if not hmac.compare_digest(self._sign(body).encode(), parts[3].encode()):
            return None
        if int(parts[1]) < time.time():
            return None
        return Session(parts[0], int(parts[1]), parts[2] == "1")

    def csrf(self, session: Session) -> str:
        """The CSRF token bound to ``session``."""
        return self._sign("csrf." + session.sid)

    def csrf_ok(self, session: Session | None, given: str | None) -> bool:
        """True when ``given`` is ``session``'s CSRF token (constant-time)."""
        if session is None or not given:
            return False
        return hmac.compare_digest(self.csrf(session).encode(), given.encode())


class Throttle:
    """Counts wrong tokens per client; after ``max_failures`` within ``window_s`` the client gets 429.

    Parameters
    ----------
    max_failures : int
        Failures allowed per window.
    window_s : float
        Sliding window, s; a blocked client is let in again when its oldest
        failure leaves the window.
    max_clients : int
        Clients remembered (the oldest is forgotten first), so memory stays bounded.
    """

    def __init__(self, max_failures: int = 5, window_s: float = 60.0, max_clients: int = 4096) -> None:
        self.max_failures, self.window_s, self.max_clients = int(max_failures), float(window_s), int(max_clients)
        self._failures: OrderedDict[str, deque[float]] = OrderedDict()

    def _recent(self, client: str, now: float) -> deque[float]:
        q = self._failures.get(client, deque())
        while q and q[0] <= now - self.window_s:
            q.popleft()
        return q

    def retry_after(self, client: str) -> int:
        """Seconds until ``client`` may try again (0: not blocked)."""
        now = time.monotonic()
        q = self._recent(client, now)
        return 0 if len(q) < self.max_failures else max(1, int(q[0] + self.window_s - now + 0.999))

    def fail(self, client: str) -> None:
        """Record one wrong token from ``client``."""
        now = time.monotonic()
        q = self._recent(client, now)
        q.append(now)
        self._failures[client] = q
        self._failures.move_to_end(client)
        while len(self._failures) > self.max_clients:
            self._failures.popitem(last=False)
