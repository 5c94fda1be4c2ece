"""Dashboard API through FastAPI's TestClient."""

from __future__ import annotations

import warnings

import pytest

pytest.importorskip("fastapi")
with warnings.catch_warnings():  # starlette warns that plain httpx is deprecated for its TestClient
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient  # noqa: E402

from layerwatch.storage.history import History  # noqa: E402
from layerwatch.web.app import create_app  # noqa: E402

TOKEN = "s3cret-token"


@pytest.fixture
def client(history, printer, image_root):
    app = create_app(history, printers={"virtual": printer}, token=TOKEN, image_root=image_root, poll_s=0.0)
    with TestClient(app, headers={"Authorization": f"Bearer {TOKEN}"}) as c:
        yield c


def test_wrong_or_missing_token_is_401(history):
    app = create_app(history, token=TOKEN)
    with TestClient(app) as c:
        assert c.get("/api/jobs").status_code == 401
        assert c.get("/api/jobs", headers={"Authorization": "Bearer nope"}).status_code == 401
        assert c.get("/").status_code == 401
        assert c.get("/login", params={"token": "nope"}).status_code == 401
        r = c.get("/login", params={"token": TOKEN}, follow_redirects=False)
        assert r.status_code == 303 and "layerwatch_token" in r.headers["set-cookie"]
        assert c.get("/api/jobs").status_code == 200  # cookie now set


def test_jobs_layers_events(client):
    (job,) = client.get("/api/jobs").json()
    assert job["n_layers"] == 10 and job["max_anomaly_ratio"] == pytest.approx(0.15)
    rows = client.get(f"/api/jobs/{job['id']}/layers").json()
    assert [r["layer"] for r in rows] == list(range(10))
    full = client.get(f"/api/jobs/{job['id']}/layers", params={"full": True}).json()
    assert full[9]["images"]["overlay"] == "layer_0009_overlay.png"
    assert client.get(f"/api/jobs/{job['id']}/latest").json()["layer"] == 9
    ev = client.get(f"/api/jobs/{job['id']}/events").json()
    assert [e["kind"] for e in ev] == ["notify", "pause"]


def test_unknown_job_404(client):
    for path in ("/api/jobs/999", "/api/jobs/999/layers", "/api/jobs/999/events", "/api/jobs/999/latest"):
        assert client.get(path).status_code == 404, path


def test_printer_actions_call_printer(client, printer):
    job = client.get("/api/jobs").json()[0]["id"]
    r = client.post("/api/printers/virtual/pause", params={"job_id": job})
    assert r.status_code == 200 and r.json()["status"] == {"state": "paused"}
    assert client.post("/api/printers/virtual/resume").json()["status"]["state"] == "printing"
    assert client.post("/api/printers/virtual/acknowledge").status_code == 200
    assert printer.calls == ["pause", "resume"]
    assert client.post("/api/printers/virtual/explode").status_code == 404
    assert client.post("/api/printers/nobody/pause").status_code == 404
    assert client.get(f"/api/jobs/{job}/events").json()[-1]["kind"] == "pause"
    assert client.get("/api/printers").json() == [{"name": "virtual", "status": {"state": "printing"}}]


def test_images_served_only_under_root(client):
    r = client.get("/api/image/layer_0009_overlay.png")
    assert r.status_code == 200 and r.content[:4] == b"\x89PNG"
    for bad in ("../secret.txt", "..%2Fsecret.txt", "%2E%2E/secret.txt", "/etc/passwd", "nothere.png"):
        assert client.get("/api/image/" + bad).status_code == 404, bad


def test_settings_round_trip_and_422(client):
    s = client.get("/api/settings").json()
    s["analysis"]["threshold"] = 0.5
    assert client.put("/api/settings", json=s).json()["analysis"]["threshold"] == 0.5
    s["analysis"]["threshold"] = 7
    assert client.put("/api/settings", json=s).status_code == 422
    r = client.put("/api/settings", content=b"{not json", headers={"Content-Type": "application/json"})
    assert r.status_code == 422
    assert client.get("/api/settings").json()["analysis"]["threshold"] == 0.5


def test_large_body_413(client):
    r = client.put("/api/settings", content=b"x" * (1 << 20 + 1), headers={"Content-Type": "application/json"})
    assert r.status_code == 413


def test_corrupt_db_is_503(tmp_path):
    p = tmp_path / "h.db"
    h = History(p)
    h.start_job("p")
    app = create_app(h)
    h._db.close()  # simulate the database becoming unusable under the app
    with TestClient(app) as c:
        r = c.get("/api/jobs")
        assert r.status_code == 503 and "history database" in r.json()["detail"]


def test_stream_reports_change(client):
    with client.stream("GET", "/api/stream", params={"limit": 2}) as r:
        text = "".join(r.iter_text())
    assert text.startswith("event: change\ndata: [")


def test_index_and_static(client):
    assert "layerwatch" in client.get("/").text
    assert "drawCurve" in client.get("/static/app.js").text
    assert client.get("/docs").status_code == 200
    assert client.get("/openapi.json").json()["info"]["title"] == "layerwatch"
