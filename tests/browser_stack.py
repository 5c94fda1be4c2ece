"""Shared pieces of the real-browser tests: Debian chromium, a uvicorn server in a thread, the screenshot folder.

Used by ``tests/web/test_browser.py`` and ``tests/farm/test_farm_browser.py``.
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

CHROMIUM = Path("/usr/bin/chromium")
#: Marks for a module of browser tests: skipped where Debian chromium is not installed.
BROWSER_MARKS = [
    pytest.mark.browser,
    pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian chromium (/usr/bin/chromium) is not installed"),
    pytest.mark.filterwarnings("ignore::DeprecationWarning"),
]
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--no-first-run", "--disable-sync"]


def launch(pw):
    """Headless Debian chromium through a Playwright handle."""
    return pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=ARGS)


@contextmanager
def serve(app, ready_path: str) -> Iterator[str]:
    """Run ``app`` with uvicorn in a thread on a free loopback port; yield its URL once ``ready_path`` answers 200."""
    uvicorn = pytest.importorskip("uvicorn")
    import httpx

    # IPPROTO_TCP as uvicorn binds it itself: asyncio sets TCP_NODELAY only then (else ~40 ms Nagle stalls)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.bind(("127.0.0.1", 0))
    srv = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off"))
    th = threading.Thread(target=srv.run, kwargs={"sockets": [sock]}, daemon=True)
    th.start()
    url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    for _ in range(200):
        try:
            if httpx.get(url + ready_path, timeout=1).status_code == 200:
                break
        except httpx.HTTPError:
            th.join(0.05)
    try:
        yield url
    finally:
        srv.should_exit = True
        th.join(10)
        sock.close()


def screenshot_dir(tmp_path: Path) -> Path:
    """``docs/screenshots/`` when ``LAYERWATCH_SCREENSHOTS=1``, else ``tmp_path``."""
    if os.environ.get("LAYERWATCH_SCREENSHOTS") == "1":
        out = Path(__file__).resolve().parents[1] / "docs" / "screenshots"
        out.mkdir(parents=True, exist_ok=True)
        return out
    return tmp_path
