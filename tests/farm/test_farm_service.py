"""A farm in one service: printers isolated from each other's faults, and the dashboard's printer routes."""

from __future__ import annotations

import time

import pytest

from layerwatch.farm import Farm, parse_farm
from layerwatch.pipeline.config import recommended_config
from layerwatch.simulate import default_camera
from layerwatch.storage.history import History

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("servers")]


def _wait(farm, done, timeout=150.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        cards = {c["name"]: c for c in farm.summaries()}
        if done(cards):
            return cards
        time.sleep(0.25)
    raise AssertionError(f"farm did not settle: {[(c['name'], c['state'], c['layer']) for c in farm.summaries()]}")


@pytest.fixture
def farm(tmp_path):
    empty = tmp_path / "no-photos"
    empty.mkdir()
    cam = tmp_path / "camera.toml"
    default_camera(recommended_config().topview.topview()).save(cam)
    (tmp_path / "bad.gcode").write_text("; nothing printed here\nG28\n")
    from layerwatch.examples import PART_GCODE

    printers = [
        {"name": "fail", "layer_seconds": 0.5, "failure": "spaghetti", "onset": 8},
        {"name": "ok1", "layer_seconds": 0.5},
        {"name": "ok2", "layer_seconds": 0.5},
        {"name": "badgcode", "gcode": "bad.gcode"},
        {"name": "deadcam", "camera": f"file:{empty}", "camera_model": str(cam), "layer_seconds": 0.5},
        {"name": "nohost", "printer": "moonraker://127.0.0.1:9", "gcode": str(PART_GCODE)},
    ]
    h = History(tmp_path / "h.db")
    f = Farm(parse_farm({"farm": {"workers": 2}, "printers": printers}, tmp_path), h, retry_s=(0.5, 2.0))
    f.start()
    yield f, h
    f.stop()
    h.close()


@pytest.mark.exclusive  # printers at 0.5 s a layer must be analysed as they print (tests/xdist_groups.py)
def test_one_failure_pauses_only_its_printer_and_faults_stay_with_their_printer(farm, make_client):
    f, h = farm
    cards = _wait(f, lambda c: c["fail"]["state"] == "paused" and c["ok1"]["state"] == c["ok2"]["state"] == "idle"
                  and c["ok1"].get("outcome") == c["ok2"].get("outcome") == "done" and c["deadcam"]["state"] == "error")
    # printed to the end (Monitor.run stops polling triggers once the printer reports "finished", so on a busy
    # machine the last layers of a 0.5 s/layer virtual print may go unseen; real layers take far longer)
    assert cards["ok1"]["layer"] >= 20 and cards["ok2"]["layer"] >= 20
    assert cards["fail"]["alarm"]["action"] == "pause" and 8 <= cards["fail"]["alarm"]["layer"] <= 14
    assert cards["ok1"]["alarm"] is None and cards["ok2"]["alarm"] is None
    assert cards["badgcode"]["state"] == "error" and "no printed layers" in cards["badgcode"]["message"]
    assert cards["deadcam"]["state"] == "error" and cards["deadcam"]["message"].startswith("camera")
    assert cards["nohost"]["state"] == "error" and "unreachable" in cards["nohost"]["message"]
    assert f.stations["ok1"].thumb.startswith(b"\x89PNG")
    jobs = {j["printer"]: j for j in h.jobs()}
    for name in ("ok1", "ok2"):  # every layer judged, or dropped with a recorded event when the workers fell behind
        drops = [e for e in h.events(jobs[name]["id"]) if e["kind"] == "frame_dropped"]
        assert jobs[name]["outcome"] == "done" and 20 <= jobs[name]["n_layers"] + len(drops) <= 33
        assert len(drops) == cards[name]["dropped"]

    from layerwatch.web.app import create_app

    c = make_client(create_app(h, printers=f.printers))
    rows = {r["name"]: r for r in c.get("/api/printers").json()}
    assert set(rows) == {"fail", "ok1", "ok2", "badgcode", "deadcam", "nohost"}
    for r in rows.values():
        assert {"name", "state", "job", "layer", "ratio", "alarm"} <= set(r)
    assert rows["fail"]["state"] == "paused" and rows["ok1"]["state"] == "idle"
    assert c.get("/api/printers/ok1/thumb.png").headers["content-type"] == "image/png"
    assert c.get("/api/printers/badgcode/thumb.png").status_code == 404
    # buttons: behind the CSRF guard, audit-logged
    no_csrf = make_client(create_app(h, printers=f.printers), csrf=False)
    assert no_csrf.post("/api/printers/fail/resume").status_code == 403
    assert f.stations["fail"].printer.status().state == "paused"
    assert c.post("/api/printers/fail/resume").status_code == 200
    assert any(a["action"] == "resume" and a["target"] == "printer fail" for a in h.audit())
    _wait(f, lambda c: c["fail"]["state"] in ("printing", "idle", "paused") and c["fail"]["layer"] > cards["fail"]["layer"])


def test_serve_farm_command_answers_api_printers_and_stops_on_sigint(tmp_path):
    import os
    import signal
    import socket
    import subprocess
    import sys

    import httpx

    (tmp_path / "farm.toml").write_text('[[printers]]\nname = "a"\nlayer_seconds = 0.5\n'
                                        '[[printers]]\nname = "b"\nlayer_seconds = 0.5\n')
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.Popen([sys.executable, "-m", "layerwatch", "serve", "--db", str(tmp_path / "h.db"),
                             "--port", str(port), "--farm", str(tmp_path / "farm.toml")],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    try:
        rows, t0 = [], time.monotonic()
        while time.monotonic() - t0 < 120:
            try:
                rows = httpx.get(f"http://127.0.0.1:{port}/api/printers", timeout=2).json()
                if [r["state"] for r in rows] == ["printing", "printing"] and all(r["layer"] is not None for r in rows):
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.5)
        assert [r["name"] for r in rows] == ["a", "b"] and all(r["state"] == "printing" for r in rows), rows
        assert httpx.get(f"http://127.0.0.1:{port}/farm", timeout=2).status_code == 200
    finally:
        proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=60)[0].decode()
    assert proc.returncode == 0, out[-2000:]
