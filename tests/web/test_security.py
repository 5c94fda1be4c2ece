"""The dashboard's door (issue 19): Host allow-list, cross-site and CSRF checks, sessions, throttling,
headers, confined image serving, bounded settings, the pause switch, redaction and the audit log."""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import socket
import warnings

import pytest
from dashclient import BASE, dashboard_client

from layerwatch.pipeline.config import JobConfig, recommended_config
from layerwatch.storage.history import History
from layerwatch.web.app import SETTINGS_KEY, create_app
from layerwatch.web.settings import RANGES
from layerwatch.web.token import is_loopback, same_token

pytest.importorskip("fastapi")
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient  # noqa: E402

EVIL = "https://evil.example"


def _app(seeded, printer, **kw):
    h, root, _ = seeded
    return create_app(h, printers={"virtual": printer}, image_root=root, **kw)


def _unsafe_requests(ids):
    """Every state-changing route of the dashboard with a valid body."""
    live = ids["live"]
    return [("POST", f"/api/printers/virtual/{a}?job_id={live}", None) for a in ("pause", "resume", "cancel", "acknowledge")] + [
        ("POST", f"/api/jobs/{live}/acknowledge", None),
        ("PATCH", "/api/settings", {"policy": {"pause_ratio": 0.2}}),
        ("PUT", "/api/settings", {"policy": {"pause_ratio": 0.2}}),
        ("PUT", "/api/pausing", {"enabled": False}),
    ]


# -- Host allow-list (DNS rebinding) -------------------------------------------------------------------

@pytest.mark.parametrize("host", ["evil.example", "evil.example:8765", "127.0.0.1.evil.example", "192.168.1.20", ""])
def test_foreign_host_refused_on_loopback(seeded, printer, host):
    c = dashboard_client(_app(seeded, printer))  # a page from the rebinding site would carry that Host
    assert c.get("/api/jobs", headers={"host": host}).status_code == 421
    r = c.post("/api/printers/virtual/pause", headers={"host": host})
    assert r.status_code == 421 and printer.status().state == "printing"


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.1:8765", "localhost:8765", "LOCALHOST", "[::1]:8765"])
def test_loopback_host_names_answered(seeded, printer, host):
    assert dashboard_client(_app(seeded, printer)).get("/api/jobs", headers={"host": host}).status_code == 200


def test_network_mode_allows_the_named_hosts(seeded, printer):
    tok = "k" * 43
    c = dashboard_client(_app(seeded, printer, token=tok, allowed_hosts=["printer.local"]), tok)
    assert c.get("/api/jobs", headers={"host": "printer.local:8765"}).status_code == 200
    assert c.get("/api/jobs", headers={"host": "evil.example"}).status_code == 421


# -- cross-site requests and CSRF ----------------------------------------------------------------------

def test_every_state_change_refused_without_csrf_token_in_default_mode(seeded, printer):
    h = seeded[0]
    c = dashboard_client(_app(seeded, printer), csrf=False)
    c.get("/")  # the victim has the dashboard open: a session cookie exists
    before = (h.revision(), h.setting(SETTINGS_KEY), h.audit())
    for method, url, body in _unsafe_requests(seeded[2]):
        r = c.request(method, url, json=body)
        assert r.status_code == 403 and "CSRF" in r.json()["detail"], (method, url, r.status_code)
    assert printer.status().state == "printing" and (h.revision(), h.setting(SETTINGS_KEY), h.audit()) == before


@pytest.mark.parametrize("headers", [
    {"Origin": EVIL}, {"Origin": "null"}, {"Sec-Fetch-Site": "cross-site"}, {"Sec-Fetch-Site": "same-site"},
    {"Origin": "http://127.0.0.1:9999"},  # another local service's page
])
def test_cross_site_refused_even_with_the_csrf_token(seeded, printer, headers):
    c = dashboard_client(_app(seeded, printer))
    for method, url, body in _unsafe_requests(seeded[2]):
        r = c.request(method, url, json=body, headers=headers)
        assert r.status_code == 403 and "refused" in r.json()["detail"], (method, url, headers)
    assert printer.status().state == "printing"


def test_same_origin_page_requests_pass(seeded, printer):
    c = dashboard_client(_app(seeded, printer))
    same = {"Origin": BASE, "Sec-Fetch-Site": "same-origin"}
    for method, url, body in _unsafe_requests(seeded[2]):
        if url.endswith("/cancel?job_id=2"):
            continue  # a cancelled virtual printer cannot resume: keep the sequence meaningful
        assert c.request(method, url, json=body, headers=same).status_code == 200, (method, url)


def test_csrf_token_is_bound_to_its_session(seeded, printer):
    app = _app(seeded, printer)
    a, b = dashboard_client(app), dashboard_client(app)
    assert a.headers["X-CSRF-Token"] != b.headers["X-CSRF-Token"]
    r = a.post("/api/printers/virtual/pause", headers={"X-CSRF-Token": b.headers["X-CSRF-Token"]})
    assert r.status_code == 403
    forged = TestClient(app, base_url=BASE, cookies={"layerwatch_session": "x.9999999999.1.forged"})
    assert forged.post("/api/printers/virtual/pause", headers={"X-CSRF-Token": "x"}).status_code == 403
    assert printer.status().state == "printing"


def test_bearer_token_scripts_need_no_csrf_but_cookies_do(seeded, printer):
    tok = "s" * 43
    app = _app(seeded, printer, token=tok)
    script = TestClient(app, base_url=BASE, headers={"Authorization": f"Bearer {tok}"})
    assert script.post("/api/printers/virtual/pause").status_code == 200  # browsers never add this header
    browser = dashboard_client(app, tok, csrf=False)  # logged in by cookie
    assert browser.post("/api/printers/virtual/resume").status_code == 403
    assert printer.status().state == "paused"


# -- token, sessions, throttling -----------------------------------------------------------------------

def test_session_cookie_is_signed_expiring_httponly_strict_and_not_the_token(seeded, printer):
    tok = "q" * 43
    app = _app(seeded, printer, token=tok, session_s=3600)
    c = TestClient(app, base_url=BASE)
    r = c.get(f"/login?token={tok}", follow_redirects=False)
    cookie = r.headers["set-cookie"]
    assert tok not in cookie and "HttpOnly" in cookie and "SameSite=strict" in cookie and "Max-Age=3600" in cookie
    assert "Secure" not in cookie  # plain http on loopback
    tls = TestClient(app, base_url="https://127.0.0.1")
    assert "Secure" in tls.get(f"/login?token={tok}", follow_redirects=False).headers["set-cookie"]
    value = c.cookies["layerwatch_session"]
    sid, exp, auth, sig = value.split(".")
    for bad in (f"{sid}.{exp}.1.{sig[:-2]}AA", f"{sid}.{int(exp) + 10}.1.{sig}", tok):  # forged, extended, token
        assert TestClient(app, base_url=BASE, cookies={"layerwatch_session": bad}).get("/api/jobs").status_code == 401
    assert TestClient(app, base_url=BASE, cookies={"layerwatch_session": value}).get("/api/jobs").status_code == 200
    expired = _app(seeded, printer, token=tok, session_s=-1)
    e = TestClient(expired, base_url=BASE)
    e.get(f"/login?token={tok}")
    assert e.get("/api/jobs").status_code == 401


def test_login_form_posts_the_token_in_the_body(seeded, printer):
    tok = "f" * 43
    c = TestClient(_app(seeded, printer, token=tok), base_url=BASE)
    page = c.get("/login").text
    csrf = page.split('name="csrf" value="', 1)[1].split('"', 1)[0]
    assert c.post("/login", data={"token": tok, "csrf": "wrong"}, follow_redirects=False).status_code == 403
    r = c.post("/login", data={"token": tok, "csrf": csrf}, follow_redirects=False)
    assert r.status_code == 303 and c.get("/api/jobs").status_code == 200
    assert tok not in r.headers["location"]


def test_wrong_tokens_throttled_per_client(seeded, printer):
    tok = "w" * 43
    app = _app(seeded, printer, token=tok)
    attacker = TestClient(app, base_url=BASE, client=("10.0.0.66", 4000))
    for _ in range(5):
        assert attacker.get("/api/jobs", headers={"Authorization": "Bearer nope"}).status_code == 401
    r = attacker.get("/api/jobs", headers={"Authorization": f"Bearer {tok}"})  # even the right one, now
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
    assert attacker.get(f"/login?token={tok}", follow_redirects=False).status_code == 429
    other = TestClient(app, base_url=BASE, client=("10.0.0.7", 4000))
    assert other.get("/api/jobs", headers={"Authorization": f"Bearer {tok}"}).status_code == 200


def test_token_compared_in_constant_time(monkeypatch):
    seen = []
    real = hmac.compare_digest
    monkeypatch.setattr(hmac, "compare_digest", lambda a, b: seen.append((len(a), len(b))) or real(a, b))
    assert same_token("right" * 9, "right" * 9) and not same_token("x", "right" * 9)
    assert not same_token("rig", "right")  # a prefix is not the token
    assert seen == [(32, 32)] * 3  # fixed-length digests: no early exit on length or position
    assert hashlib.sha256(b"x").digest_size == 32


@pytest.mark.parametrize(("host", "loop"), [
    ("127.0.0.1", True), ("127.8.9.10", True), ("::1", True), ("[::1]", True), ("localhost", True),
    ("127.evil.example", False), ("127.0.0.1.nip.invalid", False), ("0.0.0.0", False), ("::", False),
    ("192.168.1.2", False), ("", False), ("not a host", False),
])
def test_loopback_from_the_resolved_address(host, loop):
    assert is_loopback(host) is loop


# -- headers -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("path", ["/", "/api/jobs", "/static/app.js", "/api/jobs/999", "/login"])
def test_security_headers(seeded, printer, path):
    r = dashboard_client(_app(seeded, printer)).get(path, follow_redirects=False)
    assert "frame-ancestors 'none'" in r.headers["content-security-policy"]
    assert "script-src 'self'" in r.headers["content-security-policy"]
    assert r.headers["x-content-type-options"] == "nosniff" and r.headers["x-frame-options"] == "DENY"
    assert r.headers["referrer-policy"] == "no-referrer"


# -- image serving confined to the artifacts folder ----------------------------------------------------

def test_only_recorded_artifacts_inside_the_folder_are_served(seeded, printer, tmp_path):
    h, root, ids = seeded
    h.add_event(ids["live"], "x", "y")  # the WAL holds data now
    (root / "history.token").write_text("TOKEN\n")
    (root / "stray.png").write_bytes(b"\x89PNG not an artifact")
    outside = tmp_path.parent / f"{tmp_path.name}-outside.png"
    outside.write_bytes(b"\x89PNG outside")
    (root / "job1" / "escape.png").symlink_to(outside)
    (root / "job1" / "db.png").symlink_to(root / "history.db")
    from layerwatch.analysis.result import LayerResult

    h.add_layer(ids["live"], LayerResult(layer=99, z=30.0, images={
        "a": "job1/escape.png", "b": "job1/db.png", "c": "history.db", "d": "../" + outside.name, "e": str(outside)}))
    c = dashboard_client(_app(seeded, printer))  # artifacts folder = the database's folder, the worst case
    good = c.get(f"/api/jobs/{ids['live']}/layers?full=true").json()[0]["images"]["overlay"]
    assert c.get(f"/api/image/{good}").status_code == 200
    for bad in ("history.db", "history.db-wal", "history.db-shm", "history.token", "stray.png", "job1/escape.png",
                "job1/db.png", "../" + outside.name, str(outside), "%2F" + str(outside).lstrip("/"),
                "job1/../history.db", "job1/%2e%2e/history.db", ".hidden/x.png", "job1//layer0000/top.png"):
        r = c.get(f"/api/image/{bad}")
        assert r.status_code == 404 and b"SQLite" not in r.content and b"TOKEN" not in r.content, bad


def test_home_folder_as_artifacts_folder_serves_no_private_files(seeded, printer, tmp_path):
    home = tmp_path / "home"
    (home / ".ssh").mkdir(parents=True)
    (home / ".ssh" / "id_ed25519").write_text("PRIVATE KEY")
    h = History(home / "history.db")
    c = dashboard_client(create_app(h, image_root=home))
    for bad in (".ssh/id_ed25519", "history.db", "%2Essh/id_ed25519"):
        assert c.get(f"/api/image/{bad}").status_code == 404
    h.close()


# -- settings: finite, bounded, pause off only by the switch -------------------------------------------

@pytest.mark.parametrize("raw", ["Infinity", "-Infinity", "NaN", "1e9", "1e308"])
@pytest.mark.parametrize("key", ["policy.min_area_mm2", "policy.pause_ratio", "policy.consecutive_layers",
                                 "policy.strong_outside_area_mm2", "policy.skip_first_layers", "analysis.threshold",
                                 "topview.px_per_mm", "notify.min_interval_s"])
def test_non_finite_or_huge_settings_refused_naming_the_range(tmp_path, key, raw):
    h = History(tmp_path / "h.db")
    c = dashboard_client(create_app(h))
    section, name = key.split(".")
    body = f'{{"{section}": {{"{name}": {raw}}}}}'.encode()
    for method in (c.patch, c.put):
        r = method("/api/settings", content=body, headers={"content-type": "application/json"})
        assert r.status_code == 422, (key, raw, r.text)
        lo, hi, _ = RANGES[key]
        detail = r.json()["detail"]
        assert detail.startswith(f"invalid setting {key}:") and f"allowed: {lo:g} to {hi:g}" in detail, detail
    assert h.setting(SETTINGS_KEY) is None  # nothing stored
    h.close()


def test_every_numeric_setting_has_a_documented_range_holding_the_defaults():
    def numbers(v, path=()):
        if isinstance(v, dict):
            return [n for k, x in v.items() for n in numbers(x, (*path, k))]
        if isinstance(v, list):
            return [n for x in v for n in numbers(x, path)]
        return [(".".join(path), v)] if isinstance(v, int | float) and not isinstance(v, bool) else []

    for cfg in (JobConfig(), recommended_config(), JobConfig.model_validate(
            {"snapshot": {"park_xy_mm": [0, 0]}, "markers": {"positions_mm": [[1, 2]]}, "render": {"markers_mm": [[1, 2]]}})):
        for key, x in numbers(cfg.model_dump(mode="json")):
            assert key in RANGES, f"{key} has no dashboard range: add it to layerwatch.web.settings.RANGES"
            assert RANGES[key][0] <= x <= RANGES[key][1] and math.isfinite(x), (key, x)


def test_pausing_is_switched_off_only_by_the_switch(tmp_path):
    h = History(tmp_path / "h.db")
    c = dashboard_client(create_app(h))
    for body in ({"policy": {"action": "notify"}}, {"policy": {"strong_action": "notify"}},
                 {"policy": {"pause_ratio": 1.0}}, {"policy": {"consecutive_layers": 1000}}):
        assert c.patch("/api/settings", json=body).status_code == 422, body
    assert c.get("/api/pausing").json() == {"enabled": True}
    assert c.put("/api/pausing", json={"enabled": False}).json() == {"enabled": False}
    saved = JobConfig.model_validate(h.setting(SETTINGS_KEY)).policy
    assert (saved.action, saved.strong_action) == ("notify", "notify")
    assert c.patch("/api/settings", json={"policy": {"pause_ratio": 0.05}}).status_code == 200  # stays off
    assert c.get("/api/pausing").json() == {"enabled": False}
    assert c.put("/api/pausing", json={"enabled": True}).json() == {"enabled": True}
    assert [a["action"] for a in c.get("/api/audit").json()] == ["pausing on", "settings", "pausing off"]
    h.close()


# -- secrets and the audit log -------------------------------------------------------------------------

def test_no_response_of_any_route_carries_a_secret(seeded, tmp_path):
    h, root, ids = seeded
    planted = {"notify": {"apprise_urls": ["tgram://SECRET1bot/77"], "webhook_url": "http://10.0.0.1/h?t=SECRET2"},
               "printer": {"api_key": "SECRET3"}, "printer_url": "octoprint://10.0.0.2:5000?key=SECRET4"}
    job = h.start_job("octo", "part.gcode", config=planted)
    h.add_event(job, "notification", "sent", {"url": "ntfy://SECRET5", "token": "SECRET6"})
    h.add_event(job, "error", "webhook https://hooks.example/SECRET10?k=1 failed (timeout)")
    h.set_setting(SETTINGS_KEY, {"notify": {"apprise_urls": ["mailto://u:SECRET7@x"]}})

    class Keyed:
        def status(self):
            return {"state": "printing", "api_key": "SECRET8", "host": {"token": "SECRET9"}}

        def pause(self):
            pass

    tok = "SECRETTOKEN" + "t" * 32
    app = create_app(h, printers={"octo": Keyed()}, image_root=root, token=tok)
    c = dashboard_client(app, tok)
    fill = {"job_id": str(job), "name": "octo", "action": "pause", "path": "x.png"}
    assert c.get(f"/api/jobs/{job}").json()["config"]["printer"]["api_key"] == "***"
    assert "SECRET" not in c.get("/api/stream?limit=1").text
    seen = 0
    routes = [(m.upper(), p) for p, ops in app.openapi()["paths"].items() for m in ops]
    routes += [("GET", "/"), ("GET", "/login"), ("GET", "/openapi.json"), ("GET", "/docs"), ("POST", "/logout")]
    for method, path in routes:
        if path == "/api/stream":
            continue
        url = path.format(**fill)
        body = {"enabled": True} if "pausing" in path else {} if method in ("PUT", "PATCH") else None
        r = c.request(method, url, json=body, follow_redirects=False)
        seen += 1
        assert r.status_code < 500 and "SECRET" not in r.text and "SECRET" not in str(r.headers), (method, url)
    assert seen >= 18  # every route of the schema and the pages (logout last)


def test_audit_log_records_who_did_what(seeded, printer):
    h, _, ids = seeded
    tok = "a" * 43
    app = _app(seeded, printer, token=tok)
    c = dashboard_client(app, tok)
    c.post(f"/api/printers/virtual/pause?job_id={ids['live']}")
    c.post(f"/api/jobs/{ids['live']}/acknowledge")
    c.patch("/api/settings", json={"policy": {"pause_ratio": 0.2}, "notify": {"webhook_url": "http://h/SECRETX"}})
    script = TestClient(app, base_url=BASE, headers={"Authorization": f"Bearer {tok}"}, client=("10.1.2.3", 5))
    script.post("/api/printers/virtual/resume")
    rows = c.get("/api/audit").json()
    assert [r["action"] for r in rows] == ["resume", "settings", "acknowledge", "pause"]
    assert rows[0]["client"] == "10.1.2.3" and rows[0]["actor"] == "token (Authorization header)"
    assert rows[3]["target"] == "printer virtual" and rows[3]["actor"].startswith("token session ")
    assert rows[1]["detail"]["policy.pause_ratio"] == 0.2 and "SECRETX" not in str(rows)
    assert all(r["time"] > 0 for r in rows) and h.audit() == rows


def test_interrupted_job_shows_in_the_api(tmp_path):
    h = History(tmp_path / "h.db")
    job = h.start_job("p")
    gone = {"host": socket.gethostname(), "pid": 2**22 + 12345, "start": 1}  # above Linux's pid_max
    h._db.execute("UPDATE jobs SET owner = ? WHERE id = ?", (json.dumps(gone), job))
    h.close()
    h = History(tmp_path / "h.db")
    c = dashboard_client(create_app(h))
    j = c.get(f"/api/jobs/{job}").json()
    assert j["outcome"] == "interrupted" and c.get(f"/api/jobs/{job}/events").json()[-1]["kind"] == "interrupted"
    h.close()
