"""Validation of what a printer host sends back: size, content type, JSON, field types.

A printer host (OctoPrint, Moonraker, or whatever proxy sits in front of it)
can answer anything: an HTML login page with status 200, a truncated body,
``NaN`` where a number belongs, a list where an object belongs, a body of a
gigabyte. Every reply the connectors use passes through these functions,
which either return the value with the promised type or raise one
:class:`~layerwatch.errors.PrinterError` naming what was wrong (the monitor
turns that into a retried, rate-limited warning, never a crash).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Literal, overload

from layerwatch.errors import PrinterError

if TYPE_CHECKING:
    import httpx

__all__ = ["MAX_REPLY_BYTES", "read_capped", "parse_json", "reply_json", "field", "text_field", "number_field",
           "RateLimitedLog"]

#: Largest reply body read from a printer host, bytes. OctoPrint's ``/api/job`` is ~1 KB and
#: Moonraker's object query a few KB; anything near this size is not a printer status.
MAX_REPLY_BYTES = 1 << 20


def read_capped(response: httpx.Response, limit: int, where: str) -> bytes:
    """The body of a streamed response, refusing more than ``limit`` bytes.

    Parameters
    ----------
    response : httpx.Response
        Opened with ``stream=True`` (the body is not read yet).
    limit : int
        Maximum body size, bytes.
    where : str
        ``"OctoPrint GET /api/job"``, for the message.

    Raises
    ------
    PrinterError
        ``Content-Length`` or the bytes received exceed ``limit``.
    httpx.HTTPError
        The connection failed mid-body (reset, time-out); the caller maps it.
    """
    declared = response.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > limit:
        raise PrinterError(f"{where} announced a {int(declared)}-byte reply (limit {limit}); "
                           "is the URL the printer host's and not another service?")
    chunks, size = [], 0
    for chunk in response.iter_bytes():
        size += len(chunk)
        if size > limit:
            raise PrinterError(f"{where} sent more than {limit} bytes; is the URL the printer host's?")
        chunks.append(chunk)
    return b"".join(chunks)


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number")


def parse_json(body: bytes | str, where: str) -> Any:
    """Strict JSON: no ``NaN``/``Infinity``, valid UTF-8, complete.

    Raises
    ------
    PrinterError
        The body is empty, truncated, not UTF-8 or holds a non-finite number.
    """
    if not body or not body.strip():
        raise PrinterError(f"{where} sent an empty reply where JSON was expected; the host may be restarting.")
    try:
        return json.loads(body, parse_constant=_no_constant)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError, NaN
        raise PrinterError(f"{where} sent a reply that is not valid JSON ({str(exc)[:80]}); "
                           "the host may be restarting or a proxy answered.") from None


def reply_json(response: httpx.Response, where: str) -> Any:
    """The JSON body of a reply whose content type says JSON.

    Raises
    ------
    PrinterError
        Not ``application/json`` (an HTML login page from a proxy...) or not valid JSON.
    """
    ctype = response.headers.get("content-type", "")
    if "json" not in ctype.lower():
        kind = ctype.split(";")[0].strip() or "no content type"
        raise PrinterError(f"{where} answered {kind} instead of JSON; a proxy or login page may sit in front "
                           "of the printer host, check the printer URL.")
    return parse_json(response.content, where)


def field(obj: Any, key: str, kinds: type | tuple[type, ...], where: str, *, optional: bool = True) -> Any:
    """``obj[key]`` checked to be one of ``kinds`` (``None`` allowed when ``optional``).

    Raises
    ------
    PrinterError
        ``obj`` is not an object, or the value has another type.
    """
    if not isinstance(obj, dict):
        raise PrinterError(f"{where}: expected a JSON object, got {type(obj).__name__}; unexpected host reply.")
    value = obj.get(key)
    if value is None and optional:
        return None
    if not isinstance(value, kinds) or isinstance(value, bool) and bool not in _tuple(kinds):
        raise PrinterError(f"{where}: '{key}' is {_show(value)}, expected {_names(kinds)}; unexpected host reply.")
    return value


@overload
def text_field(obj: Any, key: str, where: str, *, optional: Literal[False]) -> str: ...
@overload
def text_field(obj: Any, key: str, where: str, *, optional: bool = True) -> str | None: ...
def text_field(obj: Any, key: str, where: str, *, optional: bool = True) -> str | None:
    """A string field (see :func:`field`)."""
    return field(obj, key, str, where, optional=optional)


def number_field(obj: Any, key: str, where: str, lo: float = -math.inf, hi: float = math.inf) -> float | None:
    """A finite number in ``[lo, hi]`` or ``None`` (see :func:`field`)."""
    value = field(obj, key, (int, float), where)
    if value is None:
        return None
    value = float(value)
    if not math.isfinite(value) or not lo <= value <= hi:
        raise PrinterError(f"{where}: '{key}' is {value!r}, expected a finite number in [{lo:g}, {hi:g}]; "
                           "unexpected host reply.")
    return value


def _tuple(kinds: type | tuple[type, ...]) -> tuple[type, ...]:
    return kinds if isinstance(kinds, tuple) else (kinds,)


def _names(kinds: type | tuple[type, ...]) -> str:
    names = {"str": "text", "int": "a number", "float": "a number", "dict": "an object", "list": "a list"}
    return " or ".join(dict.fromkeys(names.get(k.__name__, k.__name__) for k in _tuple(kinds)))


def _show(value: Any) -> str:
    text = json.dumps(value) if isinstance(value, (str, int, float, bool, type(None))) else type(value).__name__
    return text[:40]


class RateLimitedLog:
    """Warnings that repeat at most once per ``interval_s`` per key (the rest are counted).

    Parameters
    ----------
    logger : logging.Logger
    interval_s : float
        Least time between two warnings of one key, s.
    clock : callable
        Monotonic time source, s (tests pass a fake).
    """

    def __init__(self, logger: logging.Logger, interval_s: float = 60.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.logger, self.interval_s, self._clock = logger, float(interval_s), clock
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, key: str, message: str, *args: Any, **kw: Any) -> bool:
        """Log ``message % args`` at WARNING unless ``key`` was logged less than ``interval_s`` ago.

        Returns
        -------
        bool
            Whether it was logged.
        """
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self.interval_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        skipped = self._suppressed.pop(key, 0)
        suffix = f" ({skipped} similar warning(s) suppressed)" if skipped else ""
        self.logger.warning(message + suffix, *args, **kw)
        self._last[key] = now
        return True

    def reset(self, key: str) -> None:
        """Forget ``key`` (the condition ended; its next occurrence is logged at once)."""
        self._last.pop(key, None)
        self._suppressed.pop(key, None)
