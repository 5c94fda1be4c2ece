"""Dashboard API through FastAPI's TestClient: happy paths and bad input."""

from __future__ import annotations

import warnings

import pytest
from dashclient import dashboard_client

from layerwatch.pipeline.config import RECOMMENDED
from layerwatch.web.app import MAX_BODY, create_app

pytest.importorskip("fastapi")
with warnings.catch_warnings():  # starlette asks for httpx2, which is not installed here
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient  # noqa: E402


def client(seeded, printer, token=None):
    h, root, _ = seeded
    return dashboard_client(create_app(h, printers={"virtual": printer}, token=token, image_root=root), token)


def test_jobs_layers_events(seeded, printer):
    c = client(seeded, printer)
    ids = seeded[2]
    jobs = c.get("/api/jobs").json()
    assert [j["id"] for j in jobs] == [ids["live"], ids["done"]]
    rows = c.get(f"/api/jobs/{ids['live']}/layers").json()
    assert [r["layer"] for r in rows] == list(range(40))
    assert rows[30]["anomaly_ratio"] > rows[5]["anomaly_ratio"]
    full = c.get(f"/api/jobs/{ids['live']}/layers?full=true").json()
    assert full[35]["regions"] and full[35]["metric"] == RECOMMENDED["analysis"]["metric"]
    latest = c.get(f"/api/jobs/{ids['live']}/latest").json()
    assert latest["layer"] == 39 and "stack" in latest["images"]
    kinds = [e["kind"] for e in c.get(f"/api/jobs/{ids['live']}/events").json()]
    assert kinds[:3] == ["start", "pause", "notification"]
    assert c.get("/").status_code == 200 and "layerwatch" in c.get("/").text
    assert c.get("/static/app.js").status_code == 200


def test_images_served_and_traversal_refused(seeded, printer):
    c = client(seeded, printer)
    rel = c.get(f"/api/jobs/{seeded[2]['live']}/latest").json()["images"]["overlay"]
    r = c.get(f"/api/image/{rel}")
    assert r.status_code == 200 and r.content[:4] == b"\x89PNG"
    for bad in ("../history.db", "..%2F..%2Fetc%2Fpasswd", "%2Fetc%2Fpasswd", "job1/../../x", "missing.png"):
        assert c.get(f"/api/image/{bad}").status_code in (400, 404), bad
    (seeded[1].parent / "secret.txt").write_text("x")
    assert c.get("/api/image/../secret.txt").status_code == 404


def test_unknown_job_and_malformed(seeded, printer):
    c = client(seeded, printer)
    assert c.get("/api/jobs/999").status_code == 404
    assert c.get("/api/jobs/999/layers").status_code == 404
    assert c.get("/api/jobs/abc").status_code == 422
    assert c.put("/api/settings", content=b"{not json", headers={"content-type": "application/json"}).status_code == 422
    bad = c.get("/api/settings").json()
    bad["analysis"]["threshold"] = 3.0
    assert c.put("/api/settings", json=bad).status_code == 422
    assert c.post("/api/printers/virtual/explode").status_code == 404
    assert c.post("/api/printers/nobody/pause").status_code == 404


def test_settings_roundtrip(seeded, printer):
    c = client(seeded, printer)
    s = c.get("/api/settings").json()
    s["analysis"]["metric"] = "pearson"
    s["policy"]["pause_ratio"] = 0.2
    assert c.put("/api/settings", json=s).status_code == 200
    got = c.get("/api/settings").json()
    assert got["analysis"]["metric"] == "pearson" and got["policy"]["pause_ratio"] == 0.2
    assert "pearson" in c.get("/api/metrics").json()


def test_huge_body_413(seeded, printer):
    c = client(seeded, printer)
    r = c.put("/api/settings", content=b"x" * (MAX_BODY + 1), headers={"content-type": "application/json"})
    assert r.status_code == 413


def test_actions_change_printer_state_and_log(seeded, printer):
    c = client(seeded, printer)
    job = seeded[2]["live"]
    assert c.post(f"/api/printers/virtual/pause?job_id={job}").json()["status"]["state"] == "paused"
    assert c.post(f"/api/printers/virtual/resume?job_id={job}").json()["status"]["state"] == "printing"
    assert c.post(f"/api/printers/virtual/acknowledge?job_id={job}").status_code == 200
    kinds = [e["kind"] for e in c.get(f"/api/jobs/{job}/events").json()]
    assert kinds[-3:] == ["pause", "resume", "acknowledge"]


def test_token_required_everywhere(seeded, printer):
    tok = "t" * 43
    h, root, _ = seeded
    c = dashboard_client(create_app(h, printers={"virtual": printer}, token=tok, image_root=root), csrf=False)
    for path in ("/api/jobs", "/static/app.js", "/openapi.json", "/docs", "/api/image/x.png", "/api/session"):
        assert c.get(path).status_code == 401, path
    r = c.get("/", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/login"
    assert c.get("/api/jobs", headers={"Authorization": "Bearer wrong"}).status_code == 401
    assert c.get("/api/jobs", headers={"Authorization": f"Bearer {tok}"}).status_code == 200
    assert c.get("/login?token=wrong", follow_redirects=False).status_code == 401
    r = c.get(f"/login?token={tok}", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/"  # the token leaves the address bar
    assert c.get("/api/jobs").status_code == 200  # the session cookie now (not the token)
    assert tok not in r.headers["set-cookie"] and tok not in c.get("/").text


def test_secrets_not_exposed(seeded):
    class Keyed:
        def status(self):
            return {"state": "printing", "api_key": "SECRET123", "host": {"token": "SECRET456"}}

    h, root, _ = seeded
    c = dashboard_client(create_app(h, printers={"octo": Keyed()}, image_root=root))
    text = c.get("/api/printers").text
    assert "SECRET" not in text and "printing" in text


def test_corrupt_db_gives_503(tmp_path, printer):
    from layerwatch.storage.history import History

    h = History(tmp_path / "h.db")
    h.start_job("p")
    h.close()
    (tmp_path / "h.db-wal").unlink(missing_ok=True)
    h = History(tmp_path / "h.db")
    c = TestClient(create_app(h, printers={"virtual": printer}), base_url="http://127.0.0.1",
                   raise_server_exceptions=False)
    assert c.get("/api/jobs").status_code == 200
    h._db.close()  # the connection dies under the app (as after a disk failure)
    r = c.get("/api/jobs")
    assert r.status_code == 503 and "history database" in r.json()["detail"]


def test_token_file(tmp_path):
    import stat

    from layerwatch.web.token import is_loopback, load_or_create_token

    tok, created = load_or_create_token(tmp_path / "t.token")
    assert created and len(tok) >= 32
    assert stat.S_IMODE((tmp_path / "t.token").stat().st_mode) == 0o600
    assert load_or_create_token(tmp_path / "t.token") == (tok, False)
    assert is_loopback("127.0.0.1") and not is_loopback("0.0.0.0")


def test_stream_reports_change(seeded, printer):
    c = client(seeded, printer)
    r = c.get("/api/stream?limit=1")
    assert r.status_code == 200 and r.text.startswith("event: change")


def test_cli_history_report_and_missing_job(seeded, tmp_path):
    from layerwatch.cli import main

    h, root, ids = seeded
    db = str(h.path)
    assert main(["history", "--db", db]) == 0
    assert main(["report", str(ids["live"]), "--db", db, "-o", str(tmp_path / "rep")]) == 0
    text = (tmp_path / "rep" / "report.html").read_text()
    assert "first failing layer" in text.lower() and text.count("data:image/png;base64,") >= 5
    assert "layer 31" in text  # seeded: a% crosses 10 % at layer 31
    assert main(["report", "999", "--db", db, "-o", str(tmp_path / "x")]) == 2


def test_report_missing_image_file(seeded, tmp_path):
    from layerwatch.web.report import build_report

    h, root, ids = seeded
    for p in root.rglob("overlay.png"):
        p.unlink()
    text = build_report(h, ids["live"], tmp_path / "r").read_text()
    assert "missing" in text


def test_virtual_printer_is_the_monitor_one(seeded, printer, tmp_path):
    from layerwatch.errors import PrinterError
    from layerwatch.monitor.printers.virtual import VirtualPrinter
    from layerwatch.web.virtual import virtual_printer

    assert isinstance(printer, VirtualPrinter)
    c = client(seeded, printer)
    (p,) = c.get("/api/printers").json()
    assert p["status"]["state"] == "printing" and p["status"]["file"] == "part.gcode"
    c.post("/api/printers/virtual/cancel")
    assert printer.status().state == "cancelled"
    assert c.post("/api/printers/virtual/resume").json()["status"]["state"] == "cancelled"  # no resume after cancel
    with pytest.raises(PrinterError, match="cannot read G-code"):
        virtual_printer(tmp_path / "missing.gcode")


def test_index_names_the_newest_job(seeded, printer, tmp_path):
    c = client(seeded, printer)
    assert f'<body data-newest="{seeded[2]["live"]}">' in c.get("/").text
    from layerwatch.storage.history import History

    empty = History(tmp_path / "empty.db")
    assert empty.last_job_id() is None
    r = dashboard_client(create_app(empty), csrf=False).get("/")
    assert r.status_code == 200 and "<body>" in r.text and "data-newest" not in r.text
    empty.close()


def test_report_names_the_largest_region_kind(tmp_path):
    from layerwatch.analysis.result import LayerResult, Region
    from layerwatch.storage.history import History
    from layerwatch.web.report import build_report

    h = History(tmp_path / "h.db")
    job = h.start_job("virtual", "part.gcode")
    shift = Region(40.0, (10, 10, 20, 20), (15, 15), 4, 0.2, kind="layer_shift", kind_confidence=0.9,
                   displacement_mm=(2.0, -0.5))
    h.add_layer(job, LayerResult(layer=3, z=0.8, anomaly_ratio=0.4, regions=[shift], decision="pause"))
    text = build_report(h, job, tmp_path / "r").read_text()
    assert "largest: layer_shift 0.90 (2.0, -0.5) mm" in text
