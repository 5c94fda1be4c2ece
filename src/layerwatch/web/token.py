"""The dashboard access token: generated once, stored with 0600 permissions."""

from __future__ import annotations

import os
import secrets
from pathlib import Path

from layerwatch.errors import ConfigError

__all__ = ["load_or_create_token", "is_loopback"]


def is_loopback(host: str) -> bool:
    """True for hosts only reachable from this machine (127.0.0.0/8, ::1, localhost)."""
    return host == "localhost" or host == "::1" or host.startswith("127.")


def load_or_create_token(path: str | Path) -> tuple[str, bool]:
    """Return ``(token, created)``; a new 32-byte URL-safe token is written with mode 0600."""
    p = Path(path)
    if p.exists():
        if p.stat().st_mode & 0o077:
            raise ConfigError(f"token file {p} is readable by others; run `chmod 600 {p}`.")
        tok = p.read_text().strip()
        if len(tok) >= 16:
            return tok, False
    p.parent.mkdir(parents=True, exist_ok=True)
    tok = secrets.token_urlsafe(32)
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(tok + "\n")
    os.chmod(p, 0o600)
    return tok, True
