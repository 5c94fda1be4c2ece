"""One redaction for every dashboard response: API keys, tokens, passwords and notification URLs.

Every JSON response of the dashboard goes through :func:`redact` (the app's
default response class is :class:`RedactedJSON`), so a route that returns a
job's stored configuration, a printer's status or an event's data cannot
carry a secret even if its author forgot about one.
"""

from __future__ import annotations

import dataclasses
import json
import re
from typing import Any

from fastapi.responses import JSONResponse

__all__ = ["redact", "keep_secrets", "jsonable", "RedactedJSON", "HIDDEN"]

HIDDEN = "***"
_SECRET_KEYS = ("key", "token", "password", "passwd", "secret", "credential", "auth")
_URL_KEYS = ("_url", "_urls", "url", "urls")
_URL = re.compile(r"\b([a-zA-Z][a-zA-Z0-9+.-]*)://[^\s\"'<>]+")  # a URL in free text (event messages)


def _hide_url(url: Any) -> Any:
    """``"tgram://bot/chat"`` -> ``"tgram://***"``: notification URLs carry tokens in host and path."""
    return f"{url.split('://', 1)[0]}://{HIDDEN}" if isinstance(url, str) and "://" in url else url


def _is_secret_key(key: str) -> bool:
    return any(s in key for s in _SECRET_KEYS)


def redact(value: Any) -> Any:
    """``value`` (decoded JSON) with secrets replaced by ``"***"``.

    Values of keys that name a secret (``api_key``, ``token``, ``password``,
    ...) become ``"***"``; values of URL keys (``webhook_url``,
    ``apprise_urls``) keep only their scheme (``"tgram://***"``), and so do
    URLs inside any other string (an event message naming a webhook, an
    ``octoprint://host?key=...`` printer spec). Lists and dicts are walked
    recursively.
    """
    if isinstance(value, dict):
        out: dict[Any, Any] = {}
        for k, v in value.items():
            key = str(k).lower()
            if _is_secret_key(key) and v not in (None, "", [], {}) and not isinstance(v, bool):
                out[k] = HIDDEN
            elif key.endswith(_URL_KEYS):
                out[k] = [_hide_url(u) for u in v] if isinstance(v, list) else _hide_url(v)
            else:
                out[k] = redact(v)
        return out
    if isinstance(value, list):
        return [redact(v) for v in value]
    if isinstance(value, str) and "://" in value:
        return _URL.sub(lambda m: f"{m.group(1)}://{HIDDEN}", value)
    return value


def keep_secrets(new: Any, current: Any) -> Any:
    """``new`` where a value is exactly what :func:`redact` showed of ``current``'s replaced by ``current``'s.

    The page sends back the settings it was shown; a secret it never saw must
    not become ``"***"``.
    """
    if isinstance(new, dict) and isinstance(current, dict):
        shown = redact(current)
        return {k: (current[k] if k in current and v == shown[k] and v != current[k]
                    else keep_secrets(v, current.get(k))) for k, v in new.items()}
    return new


def jsonable(value: Any) -> Any:
    """Dataclasses and pydantic models as plain JSON values (anything else as its ``str``)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if hasattr(value, "model_dump"):
        value = value.model_dump(mode="json")
    try:
        return json.loads(json.dumps(value, default=str))
    except (TypeError, ValueError):
        return str(value)


class RedactedJSON(JSONResponse):
    """The dashboard's JSON response: content passes through :func:`redact` before it is encoded."""

    def render(self, content: Any) -> bytes:
        return super().render(redact(content))
