"""Waiting on real servers in tests: a free loopback port, and polling until a condition holds."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable

import httpx
import pytest

#: What a poll may raise while a server is still starting or a state is still changing ("not yet").
NOT_YET = (httpx.HTTPError, KeyError, ValueError, OSError)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def until(fn: Callable[[], object], deadline_s: float, what: str, every_s: float = 0.1):
    """Poll ``fn`` every ``every_s`` s until it returns something truthy; fail the test after ``deadline_s``.

    HTTP, key, value and OS errors count as "not yet"; the last value or error is in the failure message.
    """
    end = time.monotonic() + deadline_s
    last: object = None
    while time.monotonic() < end:
        try:
            last = fn()
            if last:
                return last
        except NOT_YET as exc:
            last = exc
        time.sleep(every_s)
    pytest.fail(f"timed out after {deadline_s} s waiting for {what} (last: {last!r})")
