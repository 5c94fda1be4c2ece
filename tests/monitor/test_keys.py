"""Printer API keys come from a key file, the environment or the job file; never needed on the command line."""

from __future__ import annotations

import logging
import os

import pytest
from fake_host import FakeHost

from layerwatch.cli.monitor import monitor_config, open_printer
from layerwatch.errors import ConfigError
from layerwatch.monitor.printers.keys import (
    HostSettings,
    read_key_file,
    redact_url,
    resolve_key,
    split_url_key,
)
from layerwatch.pipeline.config import JobConfig

KEY = "0123456789ABCDEF0123456789ABCDEF"


def _key_file(tmp_path, mode=0o600, text=KEY + "\n"):
    p = tmp_path / "octoprint.key"
    p.write_text(text)
    os.chmod(p, mode)
    return p


def test_precedence_key_file_env_job_file_url(tmp_path, caplog):
    env = {"LAYERWATCH_OCTOPRINT_KEY": "FROMENV"}
    url = "octoprint://h:5000?key=FROMURL"
    assert resolve_key("octoprint", url, key_file=_key_file(tmp_path), config_key="FROMFILE", env=env) == (KEY, "key file")
    assert resolve_key("octoprint", url, config_key="FROMFILE", env=env) == ("FROMENV", "LAYERWATCH_OCTOPRINT_KEY")
    assert resolve_key("octoprint", url, config_key="FROMFILE", env={}) == ("FROMFILE", "job file")
    with caplog.at_level(logging.WARNING):
        assert resolve_key("octoprint", url, env={}) == ("FROMURL", "URL")
    assert "process list" in caplog.text and "FROMURL" not in caplog.text
    assert resolve_key("moonraker", "moonraker://h", env={"LAYERWATCH_MOONRAKER_KEY": "M"}) == ("M", "LAYERWATCH_MOONRAKER_KEY")
    assert resolve_key("moonraker", "moonraker://h", env={}) == (None, "none")


def test_key_file_permissions_and_content(tmp_path, caplog):
    with pytest.raises(ConfigError, match="readable by every user; run `chmod 600"):
        read_key_file(_key_file(tmp_path, 0o644))
    with caplog.at_level(logging.WARNING):
        assert read_key_file(_key_file(tmp_path, 0o640)) == KEY
    assert "readable by its group" in caplog.text
    with pytest.raises(ConfigError, match="empty"):
        read_key_file(_key_file(tmp_path, 0o600, "\n\n"))
    with pytest.raises(ConfigError, match="printable characters"):
        read_key_file(_key_file(tmp_path, 0o600, "two words\n"))
    with pytest.raises(ConfigError, match="cannot read the key file"):
        read_key_file(tmp_path / "missing")


def test_urls_are_redacted():
    assert redact_url("octoprint://h:5000?key=SECRET") == "octoprint://h:5000?key=***"
    assert redact_url("http://user:pw@cam/snap?token=T&action=snapshot") == "http://user:***@cam/snap?token=***&action=snapshot"
    assert split_url_key("octoprint://h:5000/op?key=K&x=1") == ("octoprint://h:5000/op?x=1", "K")


def test_job_file_key_is_a_secret_in_dumps():
    cfg = JobConfig.model_validate({"host": {"api_key": KEY}})
    assert cfg.host.api_key.get_secret_value() == KEY
    assert KEY not in cfg.model_dump_json() and KEY not in repr(cfg)


def test_dashboard_cannot_set_the_host_key(tmp_path):
    from layerwatch.storage.history import History
    from layerwatch.web.app import SETTINGS_KEY

    with History(tmp_path / "h.db") as h:
        h.set_setting(SETTINGS_KEY, JobConfig(host=HostSettings(api_key="**********")).model_dump(mode="json"))
        cfg, sources = monitor_config(None, h)
    assert cfg.host.api_key is None and sources["host"] == "default"


def test_open_printer_takes_the_key_from_env_or_key_file(tmp_path, monkeypatch):
    host = FakeHost("octoprint")
    try:
        monkeypatch.setenv("LAYERWATCH_OCTOPRINT_KEY", KEY)
        with open_printer(f"octoprint://{host.hostport}") as p:
            assert p.status().state == "printing" and p._http.headers["X-Api-Key"] == KEY
        monkeypatch.delenv("LAYERWATCH_OCTOPRINT_KEY")
        with open_printer(f"octoprint://{host.hostport}", key_file=_key_file(tmp_path)) as p:
            assert p._http.headers["X-Api-Key"] == KEY
        with open_printer(f"octoprint://{host.hostport}", host=HostSettings(api_key="JOBKEY")) as p:
            assert p._http.headers["X-Api-Key"] == "JOBKEY"
    finally:
        host.close()


def test_unknown_printer_message_does_not_echo_the_key():
    with pytest.raises(ConfigError) as e:
        open_printer("telnet://h?key=SECRET")
    assert "SECRET" not in str(e.value)
