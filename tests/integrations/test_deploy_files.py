"""The shipped service files: the systemd unit, the Dockerfile (+ entry point, health check, .dockerignore)
and compose.yaml. Docker itself is not run here (no daemon on the test machines): the checks are that
every path the Dockerfile copies exists and is not ignored, that every layerwatch option the files pass
exists, and that the entry point and health check behave, run as they are in the image."""

from __future__ import annotations

import fnmatch
import http.server
import importlib.util
import os
import re
import shutil
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import typer.main
import yaml

from layerwatch.cli import app

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "integrations" / "systemd" / "layerwatch-monitor.service"
DOCKERFILE = REPO / "Dockerfile"
ENTRYPOINT = REPO / "integrations" / "docker" / "entrypoint.sh"
HEALTH = REPO / "integrations" / "docker" / "healthcheck.py"


def _options(verb: str) -> set[str]:
    cmd = typer.main.get_command(app).commands[verb]
    return {o for p in cmd.params for o in p.opts}


def _flags(words: list[str]) -> set[str]:
    return {w.split("=", 1)[0] for w in words if w.startswith("--")}


# ------------------------------------------------------------------------------------------- systemd
def parse_unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """``{section: {key: [values...]}}`` of a unit file (comments dropped, continuation lines joined)."""
    out: dict[str, dict[str, list[str]]] = {}
    section = None
    text = re.sub(r"\\\n\s*", " ", path.read_text())
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("["):
            section = line.strip("[]")
            out[section] = {}
            continue
        key, sep, value = line.partition("=")
        assert sep and section, f"not a key=value line in a section: {raw!r}"
        out[section].setdefault(key.strip(), []).append(value.strip())
    return out


def test_unit_is_hardened_and_restarts():
    svc = parse_unit(UNIT)["Service"]
    one = {k: v[-1] for k, v in svc.items()}
    assert one["User"] not in ("root", "0") and one["Group"] not in ("root", "0")
    assert one["NoNewPrivileges"] == "yes" and one["ProtectSystem"] == "strict"
    assert one["Restart"] == "on-failure" and one["RestartPreventExitStatus"] == "2"
    assert one["EnvironmentFile"].startswith("/etc/")
    assert one["CapabilityBoundingSet"] == ""
    assert "MemoryDenyWriteExecute" not in one  # Numba needs executable memory


def test_unit_runs_monitor_with_real_options_and_writes_only_where_allowed():
    svc = parse_unit(UNIT)["Service"]
    words = svc["ExecStart"][-1].split()
    assert words[0].startswith("/") and words[0].endswith("/layerwatch") and words[1] == "monitor"
    assert _flags(words) <= _options("monitor")
    history = Path(words[words.index("--history") + 1])
    writable = [Path(p) for v in svc["ReadWritePaths"] for p in v.split()]
    assert any(history.is_relative_to(w) for w in writable)
    assert f"/var/lib/{svc['StateDirectory'][-1]}" in map(str, writable)
    env_keys = {m for m in re.findall(r"\$\{(\w+)\}", svc["ExecStart"][-1])}
    assert env_keys == {"LAYERWATCH_PRINTER", "LAYERWATCH_CAMERA"}
    guide = (REPO / "docs" / "setup.md").read_text()
    assert all(f"{k}=" in guide for k in env_keys)  # the guide's env file sets them


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verifies_the_unit(tmp_path):
    # verify checks that ExecStart's binary exists: point it at this venv's layerwatch
    exe = Path(sys.executable).parent / "layerwatch"
    unit = tmp_path / "layerwatch.service"
    unit.write_text(UNIT.read_text().replace("/opt/layerwatch/venv/bin/layerwatch", str(exe)))
    res = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and not res.stderr.strip(), res.stderr
    # exposure score 0..10 ("1.9 OK" today); fail above 2.5
    sec = subprocess.run(["systemd-analyze", "security", "--offline=yes", "--threshold=25", str(unit)],
                         capture_output=True, text=True, timeout=60)
    assert sec.returncode == 0, sec.stdout[-800:]


# -------------------------------------------------------------------------------------------- Docker
def dockerfile_instructions() -> list[tuple[str, str]]:
    text = re.sub(r"\\\n\s*", " ", DOCKERFILE.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            op, _, rest = line.partition(" ")
            out.append((op.upper(), rest.strip()))
    return out


def _ignored(path: str, patterns: list[str]) -> bool:
    return any(fnmatch.fnmatch(path, p) or path.startswith(p.rstrip("/") + "/") for p in patterns)


def test_dockerfile_copies_existing_unignored_paths():
    ignore = [ln.strip() for ln in (REPO / ".dockerignore").read_text().splitlines()
              if ln.strip() and not ln.startswith("#")]
    copies = [rest.split() for op, rest in dockerfile_instructions() if op == "COPY" and "--from=" not in rest]
    assert copies
    for words in copies:
        for src in words[:-1]:
            assert (REPO / src).exists(), f"COPY {src}: no such path in the repository"
            assert not _ignored(src, ignore), f"COPY {src} is excluded by .dockerignore"
    for heavy in (".git/config", ".venv/bin/python", ".venv-octoprint", "tests/conftest.py", "history.db",
                  "layerwatch.env", "config"):  # the build context stays small and secret-free
        assert _ignored(heavy, ignore), heavy


def test_dockerfile_runs_as_non_root_with_health_check_and_entry_point():
    ins = dockerfile_instructions()
    froms = [rest for op, rest in ins if op == "FROM"]
    assert all(f.startswith("python:3.11-slim") for f in froms)
    final = ins[max(i for i, (op, _) in enumerate(ins) if op == "FROM"):]
    users = [rest for op, rest in final if op == "USER"]
    assert users and users[-1] not in ("root", "0")
    health = next(rest for op, rest in final if op == "HEALTHCHECK")
    entry = next(rest for op, rest in final if op == "ENTRYPOINT")
    copied = " ".join(rest for op, rest in final if op == "COPY")
    assert "healthcheck.py" in health and "integrations/docker/healthcheck.py" in copied
    assert "/opt/layerwatch/entrypoint.sh" in entry and "integrations/docker/entrypoint.sh" in copied
    assert os.access(ENTRYPOINT, os.X_OK)
    assert "8765" in next(rest for op, rest in final if op == "EXPOSE")


def _fake_layerwatch(tmp_path: Path) -> dict:
    """PATH with a ``layerwatch`` that records its arguments, one per line."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    fake = bindir / "layerwatch"
    fake.write_text(f'#!/bin/sh\nprintf "%s\\n" "$@" > "{tmp_path}/args"\n')
    fake.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if not k.startswith("LAYERWATCH_")}
    return dict(env, PATH=f"{bindir}{os.pathsep}{env['PATH']}")


def _entry(env: dict, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["sh", str(ENTRYPOINT), *args], env=env, capture_output=True, text=True, timeout=30)


def test_entry_point_runs_monitor_from_the_environment(tmp_path):
    env = _fake_layerwatch(tmp_path)
    conf = tmp_path / "config"
    conf.mkdir()
    (conf / "camera.toml").write_text("")
    (conf / "layerwatch.toml").write_text("")
    env.update(LAYERWATCH_PRINTER="moonraker://printer.local:7125", LAYERWATCH_CAMERA="http://cam/?action=snapshot",
               LAYERWATCH_CONFIG_DIR=str(conf), LAYERWATCH_DB=str(tmp_path / "h.db"))
    res = _entry(env)
    assert res.returncode == 0, res.stderr
    args = (tmp_path / "args").read_text().splitlines()
    assert args == ["monitor", "--follow", "--printer", "moonraker://printer.local:7125", "--camera", "http://cam/?action=snapshot",
                    "--camera-model", f"{conf}/camera.toml", "--config", f"{conf}/layerwatch.toml",
                    "--history", str(tmp_path / "h.db"), "--keep-mb", "2000"]
    assert _flags(args) <= _options("monitor")


def test_entry_point_passes_a_verb_through(tmp_path):
    env = _fake_layerwatch(tmp_path)
    assert _entry(env, "serve", "--db", "/data/history.db", "--host", "0.0.0.0").returncode == 0
    assert (tmp_path / "args").read_text().splitlines() == ["serve", "--db", "/data/history.db", "--host", "0.0.0.0"]


@pytest.mark.parametrize("missing", ["env", "config"])
def test_entry_point_refuses_an_incomplete_setup_in_one_line(tmp_path, missing):
    env = _fake_layerwatch(tmp_path)
    if missing == "config":
        env.update(LAYERWATCH_PRINTER="virtual", LAYERWATCH_CAMERA="sim", LAYERWATCH_CONFIG_DIR=str(tmp_path / "none"))
    res = _entry(env)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1
    assert ("LAYERWATCH_PRINTER" if missing == "env" else "camera.toml not found") in res.stderr
    assert not (tmp_path / "args").exists()


def test_compose_file_matches_the_image():
    comp = yaml.safe_load((REPO / "compose.yaml").read_text())
    mon, dash = comp["services"]["monitor"], comp["services"]["dashboard"]
    assert mon["build"] == "." and mon["image"] == dash["image"]
    assert "command" not in mon  # the entry point's monitor
    assert dash["command"][0] == "serve" and _flags(dash["command"]) <= _options("serve")
    assert all(p.startswith("127.0.0.1:") for p in dash["ports"])
    for svc in (mon, dash):
        assert "no-new-privileges:true" in svc["security_opt"] and svc["cap_drop"] == ["ALL"]
        assert any(v.endswith(":/data") for v in svc["volumes"])


# ------------------------------------------------------------------------------------- health check
@pytest.fixture(scope="module")
def health():
    spec = importlib.util.spec_from_file_location("layerwatch_healthcheck", HEALTH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_health_of_a_monitor_process_and_its_database(health, tmp_path):
    db = tmp_path / "history.db"
    assert health.main(["--pid", str(os.getpid()), "--db", str(db)]) == 0  # no database yet: fine
    sqlite3.connect(db).execute("CREATE TABLE jobs (id INTEGER)").connection.close()
    assert health.main(["--pid", str(os.getpid()), "--db", str(db)]) == 0
    db.write_bytes(b"not a database" * 100)
    assert health.main(["--pid", str(os.getpid()), "--db", str(db)]) == 1
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    assert health.check_process(dead.pid) is not None
    assert health.dashboard_url(["python", "layerwatch", "monitor"]) is None
    assert health.dashboard_url(["python", "layerwatch", "serve", "--port", "9000"]) == "http://127.0.0.1:9000/login"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_health_probe_of_an_http_server(health):
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        assert health.check_http(f"http://127.0.0.1:{server.server_port}/no-such-page") is None  # 404: up
    finally:
        server.shutdown()
        server.server_close()
    assert health.check_http(f"http://127.0.0.1:{_free_port()}/login", timeout_s=2) is not None


@pytest.mark.slow
def test_health_probe_of_the_real_dashboard(health, tmp_path):
    pytest.importorskip("uvicorn")
    port = _free_port()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-m", "layerwatch", "serve", "--db", str(tmp_path / "h.db"),
                             "--port", str(port)], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        url = f"http://127.0.0.1:{port}/login"
        deadline = time.monotonic() + 60
        while health.check_http(url, timeout_s=1) is not None:
            assert proc.poll() is None, proc.stdout.read().decode()
            assert time.monotonic() < deadline, "the dashboard did not come up in 60 s"
            time.sleep(0.2)
        assert health.main(["--url", url]) == 0
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        proc.stdout.close()
    assert health.main(["--url", url]) == 1
