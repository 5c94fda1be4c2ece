"""The shipped systemd units: valid, and every option they pass exists; the Docker image builds (with a daemon).

The Dockerfile, its entry point and compose.yaml are checked without Docker in test_deploy_files.py.
"""

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from layerwatch.cli import app

ROOT = Path(__file__).resolve().parents[2]
SYSTEMD = ROOT / "integrations" / "systemd"
DOCKER = ROOT  # Dockerfile and compose.yaml at the repository root


def _options(verb: str) -> set[str]:
    """Long options ``layerwatch VERB --help`` lists."""
    r = CliRunner().invoke(app, [verb, "--help"], terminal_width=200)
    assert r.exit_code == 0, r.output
    return set(re.findall(r"--[a-z][a-z-]+", r.output))


def _used(command: str) -> tuple[str, set[str]]:
    words = shlex.split(command.replace("\\\n", " "))
    i = words.index("layerwatch") + 1 if "layerwatch" in words else 0
    return words[i], {w for w in words[i + 1:] if w.startswith("--")}


def _exec_start(unit: Path) -> str:
    text = unit.read_text()
    return re.search(r"^ExecStart=(.*?)(?<!\\)$", text, re.M | re.S)[1].replace("/opt/layerwatch/venv/bin/layerwatch", "layerwatch")


@pytest.mark.parametrize("unit", ["layerwatch-monitor.service", "layerwatch-dashboard.service"])
def test_units_pass_only_options_the_cli_has(unit):
    verb, used = _used(_exec_start(SYSTEMD / unit))
    assert used and used <= _options(verb), used - _options(verb)
    if verb == "monitor":
        assert "--follow" in used


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
@pytest.mark.parametrize("unit", ["layerwatch-monitor.service", "layerwatch-dashboard.service"])
def test_units_verify(unit, tmp_path):
    exe = Path(sys.executable).with_name("layerwatch")
    if not exe.exists():
        pytest.skip(f"no layerwatch executable beside {sys.executable}")
    copy = tmp_path / unit
    copy.write_text((SYSTEMD / unit).read_text().replace("/opt/layerwatch/venv/bin/layerwatch", str(exe)))
    r = subprocess.run(["systemd-analyze", "verify", str(copy)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "Unknown" not in r.stderr, r.stderr


def _docker_ok() -> bool:
    if shutil.which("docker") is None:
        return False
    return subprocess.run(["docker", "info"], capture_output=True, timeout=30).returncode == 0


@pytest.mark.slow
@pytest.mark.skipif(not _docker_ok(), reason="no Docker daemon on this machine")
def test_docker_image_builds_and_runs_the_cli():
    subprocess.run(["docker", "build", "-f", str(DOCKER / "Dockerfile"), "-t", "layerwatch:test", str(ROOT)],
                   check=True, timeout=1800)
    r = subprocess.run(["docker", "run", "--rm", "layerwatch:test", "monitor", "--help"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0 and "--follow" in r.stdout
