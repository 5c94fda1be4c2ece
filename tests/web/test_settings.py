"""Dashboard settings: validated by the config sections, saved in the history database, kept across restarts."""

from __future__ import annotations

import pytest
from dashclient import dashboard_client

from layerwatch.pipeline.config import JobConfig, recommended_config
from layerwatch.storage.history import History
from layerwatch.web.app import SETTINGS_KEY, create_app


def _serve(db, **kw):
    h = History(db)
    return h, dashboard_client(create_app(h, **kw))


def test_settings_survive_a_server_restart(tmp_path):
    db = tmp_path / "history.db"
    h, c = _serve(db)
    s = c.get("/api/settings").json()
    assert s == recommended_config().model_dump(mode="json")  # what the monitor runs with
    s["analysis"]["metric"], s["analysis"]["threshold"] = "pearson", 0.45
    s["policy"]["pause_ratio"], s["policy"]["action"] = 0.037, "cancel"
    assert c.put("/api/settings", json=s).status_code == 200
    c.close()
    h.close()

    h, c = _serve(db)  # a new server process on the same file
    got = c.get("/api/settings").json()
    assert (got["analysis"]["metric"], got["analysis"]["threshold"]) == ("pearson", 0.45)
    assert (got["policy"]["pause_ratio"], got["policy"]["action"]) == (0.037, "cancel")
    assert JobConfig.model_validate(h.setting(SETTINGS_KEY)).policy.pause_ratio == 0.037
    h.close()


def test_saved_settings_win_over_the_servers_initial_ones(tmp_path):
    db = tmp_path / "h.db"
    initial = JobConfig.model_validate({"analysis": {"threshold": 0.3}})
    h, c = _serve(db, settings=initial)
    assert c.get("/api/settings").json()["analysis"]["threshold"] == 0.3  # nothing saved yet
    assert c.patch("/api/settings", json={"analysis": {"threshold": 0.6}}).status_code == 200
    h.close()
    h, c = _serve(db, settings=initial)
    assert c.get("/api/settings").json()["analysis"]["threshold"] == 0.6
    h.close()


@pytest.mark.parametrize(("body", "where"), [
    ({"analysis": {"threshold": 3.0}}, "analysis.threshold"),
    ({"analysis": {"bogus": 1}}, "analysis.bogus"),
    ({"bogus_section": {}}, "bogus_section"),
    ({"policy": {"action": "explode"}}, "policy.action"),
    ({"policy": {"consecutive_layers": "two"}}, "policy.consecutive_layers"),
])
def test_invalid_or_unknown_settings_get_one_line_4xx_and_change_nothing(tmp_path, body, where):
    h, c = _serve(tmp_path / "h.db")
    assert c.patch("/api/settings", json={"policy": {"pause_ratio": 0.2}}).status_code == 200
    for method in (c.put, c.patch):
        r = method("/api/settings", json=body)
        assert r.status_code == 422
        detail = r.json()["detail"]
        assert isinstance(detail, str) and "\n" not in detail
        assert detail.startswith(f"invalid setting {where}:"), detail
    assert c.get("/api/settings").json()["policy"]["pause_ratio"] == 0.2  # the saved value stays
    assert h.setting(SETTINGS_KEY)["policy"]["pause_ratio"] == 0.2
    h.close()


def test_patch_merges_put_replaces(tmp_path):
    h, c = _serve(tmp_path / "h.db")
    c.patch("/api/settings", json={"analysis": {"metric": "pearson"}})
    c.patch("/api/settings", json={"policy": {"pause_ratio": 0.25}})
    s = c.get("/api/settings").json()
    assert s["analysis"]["metric"] == "pearson" and s["policy"]["pause_ratio"] == 0.25
    assert c.put("/api/settings", json={"policy": {"pause_ratio": 0.3}}).status_code == 200
    s = c.get("/api/settings").json()
    assert s["analysis"]["metric"] == recommended_config().analysis.metric and s["policy"]["pause_ratio"] == 0.3
    h.close()


def test_notification_urls_hidden_but_kept_when_the_page_saves(tmp_path):
    h, c = _serve(tmp_path / "h.db")
    secret = {"apprise_urls": ["tgram://123456:SECRETBOT/777"], "webhook_url": "http://127.0.0.1:9/hook?t=SECRETHOOK"}
    assert "SECRET" not in c.patch("/api/settings", json={"notify": secret}).text
    shown = c.get("/api/settings").json()
    assert shown["notify"] == {**shown["notify"], "apprise_urls": ["tgram://***"], "webhook_url": "http://***"}
    shown["analysis"]["threshold"] = 0.5  # the page sends back what it was shown, with one change
    assert c.put("/api/settings", json=shown).status_code == 200
    saved = h.setting(SETTINGS_KEY)
    assert saved["analysis"]["threshold"] == 0.5
    assert saved["notify"]["apprise_urls"] == secret["apprise_urls"] and saved["notify"]["webhook_url"] == secret["webhook_url"]
    # a new URL typed in replaces the old one
    c.patch("/api/settings", json={"notify": {"apprise_urls": ["ntfy://127.0.0.1/topic"]}})
    assert h.setting(SETTINGS_KEY)["notify"]["apprise_urls"] == ["ntfy://127.0.0.1/topic"]
    h.close()


def test_stale_saved_settings_fall_back_to_defaults(tmp_path):
    h, c = _serve(tmp_path / "h.db")
    h.set_setting(SETTINGS_KEY, {"analysis": {"renamed_in_a_later_version": 1}})
    r = c.get("/api/settings")
    assert r.status_code == 200 and r.json() == recommended_config().model_dump(mode="json")
    assert c.patch("/api/settings", json={"policy": {"pause_ratio": 0.2}}).status_code == 200  # saving repairs it
    assert h.setting(SETTINGS_KEY)["policy"]["pause_ratio"] == 0.2
    h.close()


@pytest.mark.slow
def test_settings_survive_restarting_layerwatch_serve(tmp_path):
    """The real CLI server process, stopped and started again on the same database file."""
    import socket
    import subprocess
    import sys
    import time
    from pathlib import Path

    import httpx

    exe = Path(sys.executable).with_name("layerwatch")
    if not exe.exists():
        pytest.skip("the layerwatch console script is not installed in this environment")
    db = tmp_path / "history.db"

    def serve():
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        proc = subprocess.Popen([str(exe), "serve", "--db", str(db), "--port", str(port)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        url = f"http://127.0.0.1:{port}"
        end = time.monotonic() + 60
        while True:
            assert proc.poll() is None, "layerwatch serve exited"
            try:
                httpx.get(url + "/api/settings", timeout=2)
                return proc, url
            except httpx.HTTPError:
                assert time.monotonic() < end, "layerwatch serve did not start"
                time.sleep(0.1)

    proc, url = serve()
    try:
        with httpx.Client(base_url=url) as c:  # as a local script does: a session, then its CSRF token
            c.headers["X-CSRF-Token"] = c.get("/api/session").json()["csrf"]
            r = c.patch("/api/settings", json={"policy": {"pause_ratio": 0.042}, "analysis": {"metric": "dice"}})
            assert r.status_code == 200
            bad = c.patch("/api/settings", json={"policy": {"nonsense": 1}})
        assert bad.status_code == 422 and bad.json()["detail"].startswith("invalid setting policy.nonsense:")
    finally:
        proc.terminate()
        proc.wait(10)
    proc, url = serve()
    try:
        got = httpx.get(url + "/api/settings").json()
        assert got["policy"]["pause_ratio"] == 0.042 and got["analysis"]["metric"] == "dice"
    finally:
        proc.terminate()
        proc.wait(10)


def test_error_line_stays_one_line_for_odd_keys(tmp_path):
    h, c = _serve(tmp_path / "h.db")
    r = c.patch("/api/settings", json={"policy": {"two\nlines\r\nkey": 1}})
    assert r.status_code == 422 and "\n" not in r.json()["detail"] and "\r" not in r.json()["detail"]
    h.close()
