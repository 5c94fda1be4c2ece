"""The dashboard access token: generated once, stored with mode 0600, compared in constant time.

Also decides whether an address is loopback (reachable only from this
machine) from the address itself, resolved with :mod:`ipaddress`, never from
how its name is spelled.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import os
import secrets
import socket
from pathlib import Path

from layerwatch.errors import ConfigError

__all__ = ["load_or_create_token", "is_loopback", "same_token", "LOOPBACK_NAMES"]

LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})


def _loopback_ip(text: str) -> bool | None:
    """True/False for an IP literal (``[::1]`` included), ``None`` for a host name."""
    try:
        return ipaddress.ip_address(text.strip("[]")).is_loopback
    except ValueError:
        return None


def is_loopback(host: str) -> bool:
    """True when every address ``host`` resolves to is a loopback address (127.0.0.0/8, ::1).

    IP literals are judged by :mod:`ipaddress`; names are resolved
    (``getaddrinfo``) and all their addresses must be loopback, so
    ``127.evil.example`` is not loopback unless DNS really says so, and a
    name that does not resolve is not loopback. ``0.0.0.0`` and ``::``
    (every interface) are not loopback.
    """
    literal = _loopback_ip(host)
    if literal is not None:
        return literal
    try:
        infos = socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP)
    except (OSError, UnicodeError):
        return False
    return bool(infos) and all(_loopback_ip(str(info[4][0]).split("%", 1)[0]) for info in infos)


def same_token(given: str, token: str) -> bool:
    """Constant-time comparison of a presented token with the real one.

    Both are hashed (SHA-256) first, so the comparison time depends neither
    on where they differ nor on the presented token's length.
    """
    a = hashlib.sha256(given.encode("utf-8", "surrogatepass")).digest()
    b = hashlib.sha256(token.encode("utf-8", "surrogatepass")).digest()
    return hmac.compare_digest(a, b)


def load_or_create_token(path: str | Path) -> tuple[str, bool]:
    """Return ``(token, created)``; a new 32-byte URL-safe token is written with mode 0600.

    Raises
    ------
    ConfigError
        The existing file is readable or writable by other users.
    """
    p = Path(path)
    if p.exists():
        if p.stat().st_mode & 0o077:
            raise ConfigError(f"token file {p} is readable by others; run `chmod 600 {p}`.")
        tok = p.read_text().strip()
        if len(tok) >= 16:
            return tok, False
    if not p.parent.exists():
        p.parent.mkdir(parents=True, mode=0o700)
    tok = secrets.token_urlsafe(32)
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        os.fchmod(f.fileno(), 0o600)
        f.write(tok + "\n")
    return tok, True
