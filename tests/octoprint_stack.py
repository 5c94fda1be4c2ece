"""A real OctoPrint (the CI's .venv-octoprint) with its virtual printer, for the plugin and monitor tests.

:func:`octoprint_server` writes a fresh basedir (config, admin user, API key), starts
``octoprint serve`` on a free port and stops it afterwards. Missing OctoPrint or plugin:
skip locally, fail under ``CI=true`` (``.ci/run`` installs both).
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from polling import free_port, until

ROOT = Path(__file__).resolve().parents[1]
VENV = Path(os.environ.get("LAYERWATCH_OCTOPRINT_VENV", ROOT / ".venv-octoprint"))
OCTO = VENV / "bin" / "octoprint"


def require_plugin() -> None:
    """Skip (fail under CI=true) unless OctoPrint and the layerwatch plugin are installed in :data:`VENV`."""
    msg = None
    if not OCTO.exists():
        msg = f"OctoPrint not installed at {VENV}; run .ci/install-octoprint"
    elif subprocess.run([str(VENV / "bin" / "python"), "-c", "import octoprint_layerwatch.plugin"],
                        capture_output=True, timeout=120).returncode != 0:
        msg = f"the layerwatch OctoPrint plugin is not installed in {VENV}; run .ci/install-octoprint"
    if msg is not None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg + " (CI=true: .ci/run must have installed it)")
        pytest.skip(msg)


@contextlib.contextmanager
def octoprint_server(base: Path, plugins: dict | None = None,
                     virtual_printer: dict | None = None) -> Iterator[tuple[str, str]]:
    """Serve a fresh OctoPrint from ``base``; yields ``(url, api_key)``.

    ``plugins``: more ``plugins.<id>`` settings. ``serial.log`` is on (``base/logs/serial.log``
    has every line sent, with its time). ``virtual_printer``: settings of OctoPrint's virtual
    printer (default: it answers at once, ``throttle`` 1 ms; ``{}`` keeps OctoPrint's pace).
    """
    key = secrets.token_hex(16).upper()
    config = {
        "server": {"firstRun": False, "onlineCheck": {"enabled": False}, "pluginBlacklist": {"enabled": False}},
        "api": {"key": key},
        "serial": {"log": True},
        "devel": {"virtualPrinter": {"enabled": True, "okAfterResend": False,
                                     **({"throttle": 0.001} if virtual_printer is None else virtual_printer)}},
        "plugins": {"tracking": {"enabled": False}, "announcements": {"enabled": False},
                    "softwareupdate": {"checks": {}}, **(plugins or {})},
    }
    (base / "config.yaml").write_text(json.dumps(config, indent=1))  # JSON is YAML
    subprocess.run([str(OCTO), "--basedir", str(base), "user", "add", "--password", "lw-test-pw", "--admin", "lwadmin"],
                   check=True, capture_output=True, timeout=120)
    port = free_port()
    log = open(base / "serve.log", "w")
    proc = subprocess.Popen([str(OCTO), "serve", "--iknowwhatimdoing", "--basedir", str(base), "--host", "127.0.0.1",
                             "--port", str(port)], stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        until(lambda: httpx.get(url + "/api/version", headers={"X-Api-Key": key}, timeout=2).status_code == 200,
              120, "OctoPrint to serve")
        yield url, key
    finally:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
        if proc.returncode not in (0, -15):
            sys.stdout.write((base / "serve.log").read_text()[-3000:])
