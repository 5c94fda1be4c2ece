"""Docker HEALTHCHECK for the layerwatch image (standard library only; exit 0 healthy, 1 unhealthy).

What it checks depends on what the container runs (PID 1's command line):

* ``layerwatch serve``: the dashboard answers HTTP on 127.0.0.1 and its ``--port`` (any status below
  500 counts: without a token the page may refuse the request, but the server is up);
* otherwise (``layerwatch monitor``): PID 1 is alive (not a zombie) and the history database, when it
  exists, opens read-only and answers a query. Printer and camera faults of a running monitor are
  reported by the monitor itself as alerts, not by the container's health.

Run by hand: ``python healthcheck.py [--pid N] [--db FILE] [--url URL]``.
"""

from __future__ import annotations

import argparse
import os
import sqlite3
import sys
import urllib.error
import urllib.request
from pathlib import Path


def process_args(pid: int, proc: Path = Path("/proc")) -> list[str]:
    """Command line of ``pid`` (empty when unreadable)."""
    try:
        raw = (proc / str(pid) / "cmdline").read_bytes()
    except OSError:
        return []
    return [a.decode("utf-8", "replace") for a in raw.split(b"\0") if a]


def check_process(pid: int, proc: Path = Path("/proc")) -> str | None:
    """None when ``pid`` runs, else why not."""
    try:
        stat = (proc / str(pid) / "stat").read_text()
    except OSError:
        return f"process {pid} is not running"
    state = stat.rsplit(")", 1)[-1].split()[0]
    return f"process {pid} is a zombie" if state == "Z" else None


def check_db(path: Path) -> str | None:
    """None when the history database is absent (no job yet) or answers a read-only query."""
    if not path.exists():
        return None
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5) as con:
            con.execute("SELECT count(*) FROM sqlite_master").fetchone()
    except sqlite3.Error as exc:
        return f"history database {path}: {exc}"
    return None


def check_http(url: str, timeout_s: float = 5.0) -> str | None:
    """None when ``url`` answers with a status below 500."""
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as resp:  # noqa: S310 - a fixed loopback URL
            status = resp.status
    except urllib.error.HTTPError as exc:
        status = exc.code
    except (urllib.error.URLError, OSError) as exc:
        return f"{url}: {getattr(exc, 'reason', exc)}"
    return None if status < 500 else f"{url}: HTTP {status}"


def dashboard_url(args: list[str]) -> str | None:
    """``http://127.0.0.1:PORT/login`` when ``args`` run ``layerwatch serve``, else None."""
    if "serve" not in args:
        return None
    port = "8765"
    for i, a in enumerate(args):
        if a == "--port" and i + 1 < len(args):
            port = args[i + 1]
        elif a.startswith("--port="):
            port = a.split("=", 1)[1]
    return f"http://127.0.0.1:{port}/login"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Health of the layerwatch container.")
    p.add_argument("--pid", type=int, default=1, help="process to check (default: PID 1)")
    p.add_argument("--db", type=Path, default=Path(os.environ.get("LAYERWATCH_DB", "/data/history.db")))
    p.add_argument("--url", help="dashboard URL to probe (default: from PID 1's `serve --port`)")
    a = p.parse_args(argv)
    url = a.url or dashboard_url(process_args(a.pid))
    problem = check_http(url) if url else (check_process(a.pid) or check_db(a.db))
    if problem:
        print(f"unhealthy: {problem}", file=sys.stderr)
        return 1
    print("healthy")
    return 0


if __name__ == "__main__":
    sys.exit(main())
