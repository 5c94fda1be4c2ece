"""A real OctoPrint (the CI's .venv-octoprint) with its virtual printer, for the plugin and monitor tests.

:func:`octoprint_server` writes a fresh basedir (config, admin user, API key), starts
``octoprint serve`` on a free port and stops it afterwards. Missing OctoPrint or plugin:
skip locally, fail under ``CI=true`` (``.ci/run`` installs both).

OctoPrint's virtual printer spends a tenth of each move's real duration and heats at 10 °C/s
(its ``throttle`` setting is read nowhere in 1.11.8). The tests that only need a print to run
(not its pace) print at :func:`fast_moves` pace; every server's hot end starts at
:data:`HOT_END_C`, so the example part's ``M109 S200`` does not wait ~18 s of simulated heating.
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
#: the virtual printer's ambient temperature (°C): its hot end starts there, so ``M109 S200`` (the
#: example part's) returns at once; a cooling hot end drifts back to it
HOT_END_C = 200.0
#: :func:`fast_moves`' feed and flow rate (%): moves take a hundredth of their real duration
FAST_MOVES_PERCENT = 1000


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
    has every line sent, with its time). ``virtual_printer``: more settings of OctoPrint's
    virtual printer (its ambient temperature is :data:`HOT_END_C`).
    """
    key = secrets.token_hex(16).upper()
    config = {
        "server": {"firstRun": False, "onlineCheck": {"enabled": False}, "pluginBlacklist": {"enabled": False}},
        "api": {"key": key},
        "serial": {"log": True},
        "devel": {"virtualPrinter": {"enabled": True, "okAfterResend": False, "ambientTemperature": HOT_END_C,
                                     **(virtual_printer or {})}},
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
            proc.wait(15)  # reaped here: else its ResourceWarning fails whichever test the GC runs in
        log.close()
        if proc.returncode not in (0, -15):
            sys.stdout.write((base / "serve.log").read_text()[-3000:])


@contextlib.contextmanager
def fast_moves(url: str, key: str, percent: int = FAST_MOVES_PERCENT) -> Iterator[None]:
    """Run the connected virtual printer's moves ``percent`` % as fast (``M220``/``M221``) until exit.

    For tests that need a print to run, not its pace: the example part's first three layers take
    ~36 s on OctoPrint's virtual printer, 3.6 s at 1000 %. Dwells (``G4``) keep their length. The
    rates are set back to 100 % at exit (the virtual printer keeps them while it stays connected,
    and a session's server is shared).
    """
    def send(*commands: str) -> httpx.Response:
        return httpx.post(url + "/api/printer/command", headers={"X-Api-Key": key}, json={"commands": list(commands)},
                          timeout=10)

    send(f"M220 S{percent}", f"M221 S{percent}").raise_for_status()
    try:
        yield
    finally:
        send("M220 S100", "M221 S100")  # 409 when it was disconnected: a reconnected one starts at 100 %
