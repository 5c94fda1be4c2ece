"""The layerwatch OctoPrint plugin inside a real OctoPrint 1.11 with its virtual printer.

CI (``.ci/install-octoprint``) pip-installs layerwatch and the plugin into the OctoPrint venv.
The camera is OctoPrint's own (the Classic Webcam's snapshot URL), pointed at a snapshot server
run here that serves simulated photos of the example part (``layerwatch.simulate``), one per
request, some of them late; ``serial.log`` gives the time every line was sent to the printer.
"""

from __future__ import annotations

import dataclasses
import re
import socket
import threading
import time
from datetime import datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from octoprint_stack import fast_moves, free_port, octoprint_server, require_plugin, until

pytestmark = [pytest.mark.octoprint, pytest.mark.slow, pytest.mark.xdist_group("servers")]

N_LAYERS = 20  # layers of the prepared job
ONSET = 15  # first layer with the injected spaghetti
LATE_S = {3: 1.5, 4: 1.5}  # layer -> seconds the camera takes to answer
HOLD_S = 30.0  # hold time-out of the analysed job (never reached: the camera answers)
DEAD_HOLD_S = 1.0  # hold time-out with the dead camera


class SnapshotServer:
    """Serves ``frames[i]`` (PNG) to the i-th request, ``LATE_S[i]`` late; records when each was served."""

    def __init__(self, frames: list[bytes]) -> None:
        self.frames, self.served, self._lock = frames, {}, threading.Lock()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 - http.server's name
                with outer._lock:
                    i = len(outer.served)
                    outer.served[i] = None
                time.sleep(LATE_S.get(i, 0.0))
                body = outer.frames[min(i, len(outer.frames) - 1)]
                self.send_response(200)
                self.send_header("Content-Type", "image/png")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)
                self.wfile.flush()
                outer.served[i] = time.time()

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", free_port()), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/snapshot"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@dataclasses.dataclass
class Sim:
    camera_model: Path
    bed_photo: Path
    job_wait: Path  # job config: example part, hold until the verdict
    job_frame: Path  # job config: example part, hold until the frame only
    gcode: bytes  # prepared, N_LAYERS layers
    short_gcode: bytes  # prepared, 4 layers
    m240_gcode: bytes  # prepared with the m240 profile (M118 trigger, no @ line), 5 layers
    frames: list[bytes]


def _cut(prepared: bytes, n: int) -> bytes:
    """The first ``n`` layers of ``prepared``: up to the start of layer ``n``'s snapshot block."""
    cut = prepared.rfind(b"; layerwatch snapshot block:", 0, prepared.find(f"layerwatch snapshot layer={n} ".encode()))
    assert cut > 0
    return prepared[:cut]


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Sim:
    from layerwatch.examples import PART_CONFIG, PART_GCODE
    from layerwatch.gcode import read_toolpath
    from layerwatch.gcode.postprocess import insert_snapshots
    from layerwatch.pipeline.config import recommended_config
    from layerwatch.simulate import Failure, PrintSimulator, default_camera

    require_plugin()
    d = tmp_path_factory.mktemp("plugin-sim")
    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    data = PART_GCODE.read_bytes()
    tp = read_toolpath(data)
    truth = default_camera(tv)
    bad = PrintSimulator(tp, truth, tv, [Failure("spaghetti", onset=ONSET, seed=1)], seed=1)
    frames = [cv2.imencode(".png", bad.frame(i).photo)[1].tobytes() for i in range(N_LAYERS)]
    dataclasses.replace(truth, rvec=None, tvec=None).save(d / "camera.toml")  # intrinsics only: the bed photo locates it
    (d / "bed.png").write_bytes(frames[0])
    base = PART_CONFIG.read_text()
    (d / "job-wait.toml").write_text(base + "\n[policy]\nwait_for_verdict = true\n")
    (d / "job-frame.toml").write_text(base)
    # the octoprint profile's block; the dwell after the trigger kept short (the plugin holds the queue instead)
    snap = cfg.snapshot.model_copy(update={"profile": "octoprint", "settle_ms": 100})
    prepared = insert_snapshots(data, snap, cfg.printer)
    m240 = insert_snapshots(data, snap.model_copy(update={"profile": "m240"}), cfg.printer)
    return Sim(d / "camera.toml", d / "bed.png", d / "job-wait.toml", d / "job-frame.toml",
               _cut(prepared, N_LAYERS), _cut(prepared, 4), _cut(m240, 5), frames)


@dataclasses.dataclass
class Stack:
    url: str
    key: str
    base: Path
    camera: SnapshotServer

    @property
    def h(self) -> dict:
        return {"X-Api-Key": self.key}

    def get(self, path: str):
        r = httpx.get(self.url + path, headers=self.h, timeout=10)
        r.raise_for_status()
        return r.json()

    def post(self, path: str, body: dict) -> httpx.Response:
        return httpx.post(self.url + path, headers=self.h, json=body, timeout=10)

    def plugin_settings(self, **values) -> dict:
        self.post("/api/settings", {"plugins": {"layerwatch": values}}).raise_for_status()
        return self.get("/api/settings")["plugins"]["layerwatch"]

    def state(self) -> dict:
        return self.get("/api/plugin/layerwatch")

    def finished(self, name: str) -> bool:
        """The plugin has seen the print of ``name`` end (or refused to watch it)."""
        st = self.state()
        return st["job"] == name and st["status"] in ("done", "error")

    def job_state(self) -> str:
        return self.get("/api/job")["state"]

    def print_file(self, name: str, data: bytes) -> None:
        r = httpx.post(self.url + "/api/files/local", headers=self.h, files={"file": (name, data, "application/octet-stream")},
                       data={"select": "true", "print": "true"}, timeout=30)
        r.raise_for_status()


@pytest.fixture(scope="module")
def stack(sim, tmp_path_factory):
    camera = SnapshotServer(sim.frames)
    base = tmp_path_factory.mktemp("octoprint-plugin")
    try:
        # _config_version: the Classic Webcam would otherwise "migrate" (blank) its settings from the legacy webcam.*
        with octoprint_server(base, {"classicwebcam": {"_config_version": 1, "snapshot": camera.url, "snapshotTimeout": 3}}) as (url, key):
            s = Stack(url, key, base, camera)
            s.post("/api/connection", {"command": "connect", "port": "VIRTUAL", "baudrate": 115200}).raise_for_status()
            until(lambda: s.get("/api/connection")["current"]["state"] == "Operational", 60, "the virtual printer")
            with fast_moves(url, key):  # the holds, not the moves, pace these prints
                yield s
    finally:
        camera.close()


def _released_at(serial_log: Path, held_line_sent: bool, since: float) -> dict[int, float]:
    """``layer -> time.time()`` the first line after each trigger's hold was sent to the printer (job started at ``since``).

    With the ``@`` trigger (never sent itself) that is the block's ``M118`` line; with an ``M118``
    trigger (``held_line_sent``: the hook sees it as it is sent) it is the line after it.
    """
    sends = []
    rx = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) - Send: (.*)$")
    for line in serial_log.read_text(errors="replace").splitlines():
        m = rx.match(line)
        if m and datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S,%f").timestamp() >= since - 0.002:
            sends.append((datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S,%f").timestamp(), m[2]))
    out: dict[int, float] = {}
    for i, (_, text) in enumerate(sends):
        m = re.search(r"M118 E1 layerwatch snapshot layer=(\d+) ", text)
        j = i + 1 if held_line_sent else i
        if m and int(m[1]) not in out and j < len(sends):
            out[int(m[1])] = sends[j][0]
    return out


def test_plugin_loads_and_its_settings_save(stack, sim):
    plugins = httpx.get(stack.url + "/plugin/pluginmanager/plugins", headers=stack.h, timeout=30).json()["plugins"]
    (mine,) = [p for p in plugins if p["key"] == "layerwatch"]
    assert mine["enabled"] and mine["name"] == "layerwatch", mine
    assert stack.state()["status"] == "idle"
    saved = stack.plugin_settings(camera_model=str(sim.camera_model), bed_photo=str(sim.bed_photo),
                                  job_config=str(sim.job_frame), hold_timeout_s=7.5, pause_ratio="0.2")
    assert saved["camera_model"] == str(sim.camera_model) and saved["bed_photo"] == str(sim.bed_photo)
    assert saved["hold_timeout_s"] == 7.5 and saved["pause_ratio"] == 0.2  # stored as layerwatch read it
    assert stack.state()["settings_error"] is None
    # refused values are not stored; the error names the key and the fix
    for bad, key in [({"pause_ratio": 7}, "pause_ratio"), ({"camera_model": "camera.toml"}, "absolute path"),
                     ({"hold_timeout_s": "nan"}, "hold_timeout_s"), ({"bed_photo": "/no/such.png"}, "does not exist")]:
        after = stack.plugin_settings(**bad)
        assert after == saved, bad
        assert key in stack.state()["settings_error"], (bad, stack.state()["settings_error"])
    stack.plugin_settings(pause_ratio="")
    assert stack.state()["settings_error"] is None
    # the tab and the settings page are in the UI a logged-in user gets, with their view model
    with httpx.Client(base_url=stack.url, timeout=30) as web:
        web.get("/")
        web.post("/api/login", json={"user": "lwadmin", "pass": "lw-test-pw", "remember": False},
                 headers={"X-CSRF-Token": web.cookies.get("csrf_token_P" + stack.url.rsplit(":", 1)[1], "")}).raise_for_status()
        page = web.get("/").text
        assert 'id="layerwatch_tab"' in page and "settings.plugins.layerwatch.hold_timeout_s" in page
        js = web.get("/plugin/layerwatch/static/js/layerwatch.js")
        assert js.status_code == 200 and "LayerwatchViewModel" in js.text


def test_prepared_job_is_held_for_each_photo_analysed_and_paused(stack, sim):
    stack.plugin_settings(camera_model=str(sim.camera_model), bed_photo=str(sim.bed_photo), job_config=str(sim.job_wait),
                          hold_timeout_s=HOLD_S, pause_ratio="", camera="")
    t0 = time.time()
    stack.print_file("lw-spaghetti.gcode", sim.gcode)
    until(lambda: stack.job_state() == "Paused", 240, "the plugin to pause the print")
    st = stack.state()
    print(f"\nplugin: {st['layers']} layers analysed, stops {st['stops']}, {time.time() - t0:.0f} s")
    (stop,) = st["stops"]
    assert ONSET <= stop[0] <= ONSET + 1 and stop[1] == "pause", st["stops"]
    ratios = dict((layer, r) for layer, r in st["ratios"] if r is not None)
    assert len(ratios) >= ONSET - 2 and max(ratios[i] for i in range(ONSET)) < ratios[stop[0]], ratios
    holds = {h["layer"]: h for h in st["holds"]}
    assert set(range(stop[0] + 1)) <= set(holds), holds
    for layer in range(stop[0] + 1):
        assert holds[layer]["held"] and holds[layer]["outcome"] == "frame", holds[layer]
    for layer, late in LATE_S.items():
        assert holds[layer]["held_ms"] >= 1000 * late, holds[layer]
    # the printer got nothing after a trigger before that layer's photo was served
    sent = _released_at(stack.base / "logs" / "serial.log", held_line_sent=False, since=t0)
    served = stack.camera.served
    for layer in range(stop[0]):
        assert served[layer] is not None and sent[layer] >= served[layer] - 0.002, (layer, sent[layer], served[layer])
    # the verdict came during the stop layer's hold (wait_for_verdict): paused there, at the park spot
    assert max(sent) <= stop[0] and (stop[0] not in sent or sent[stop[0]] >= served[stop[0]] - 0.002), sorted(sent)
    for layer in LATE_S:
        print(f"layer {layer}: photo served {served[layer] - t0:.2f} s, next line sent {sent[layer] - t0:.2f} s "
              f"(held {holds[layer]['held_ms']:.0f} ms)")
    # the tab's overlay of the latest analysed layer
    png = httpx.get(stack.url + "/plugin/layerwatch/overlay.png", headers=stack.h, timeout=10)
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    img = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.std() > 10
    stack.post("/api/job", {"command": "cancel"}).raise_for_status()
    until(lambda: stack.job_state() == "Operational", 60, "the job to cancel")


def test_m118_trigger_of_the_other_profiles_is_held_too(stack, sim):
    """A file prepared with ``--profile m240`` (``M118`` + ``M240``, no ``@`` line) is held at its ``M118``."""
    stack.plugin_settings(camera_model=str(sim.camera_model), bed_photo=str(sim.bed_photo), job_config=str(sim.job_frame),
                          hold_timeout_s=HOLD_S, pause_ratio="", camera="")
    stack.camera.served.clear()  # frames of layers 0.. again, layers 3 and 4 late
    t0 = time.time()
    stack.print_file("lw-m240.gcode", sim.m240_gcode)
    until(lambda: stack.finished("lw-m240.gcode"), 180, "the print to finish")
    st = stack.state()
    assert st["status"] == "done", st["message"]
    holds = {h["layer"]: h for h in st["holds"]}
    assert sorted(holds) == [0, 1, 2, 3, 4] and all(h["held"] and h["outcome"] == "frame" for h in holds.values()), holds
    released = _released_at(stack.base / "logs" / "serial.log", held_line_sent=True, since=t0)
    served = stack.camera.served
    for layer in range(5):
        assert released[layer] >= served[layer] - 0.002, (layer, released[layer], served[layer])
    assert holds[3]["held_ms"] >= 1000 * LATE_S[3]
    assert st["layers"] == 5 and st["pauses"] == 0


def test_dead_camera_hold_times_out_and_the_print_goes_on(stack, sim):
    dead = socket.socket()
    dead.bind(("127.0.0.1", 0))
    dead.listen(16)  # accepts connections in the kernel, never answers
    try:
        url = f"http://127.0.0.1:{dead.getsockname()[1]}/snapshot"
        stack.post("/api/settings", {"plugins": {"classicwebcam": {"snapshot": url, "snapshotTimeout": 3}}}).raise_for_status()
        stack.plugin_settings(camera_model=str(sim.camera_model), bed_photo=str(sim.bed_photo), job_config=str(sim.job_frame),
                              hold_timeout_s=DEAD_HOLD_S, pause_ratio="", camera="")
        t0 = time.monotonic()
        stack.print_file("lw-dead-camera.gcode", sim.short_gcode)
        until(lambda: stack.finished("lw-dead-camera.gcode"), 120, "the print to finish")
        took = time.monotonic() - t0
    finally:
        dead.close()
    st = stack.state()
    assert st["status"] == "done", st["message"]  # watched (not refused at set-up) and finished
    holds = st["holds"]
    assert [h["layer"] for h in holds] == [0, 1, 2, 3], holds
    timed_out = [h for h in holds if h["outcome"] == "timeout"]
    assert timed_out and all(h["held"] and 1000 * DEAD_HOLD_S <= h["held_ms"] < 1000 * DEAD_HOLD_S + 1500 for h in timed_out), holds
    assert all(h["outcome"] in ("timeout", "skipped") for h in holds), holds  # never released by a frame
    assert st["pauses"] == 0 and stack.job_state() == "Operational"
    # what the dead camera cost the print: at most the time-out per layer (the virtual printer's own pace varies)
    assert sum(h["held_ms"] for h in holds) <= 4 * (1000 * DEAD_HOLD_S + 1500), holds
    print(f"\ndead camera: {len(timed_out)} holds timed out after {[h['held_ms'] for h in timed_out]} ms, "
          f"{sum(h['outcome'] == 'skipped' for h in holds)} skipped (photo still pending); print done in {took:.1f} s")
