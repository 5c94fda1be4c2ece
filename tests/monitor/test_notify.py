import base64
import json
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer

import pytest

from layerwatch.monitor.notify import Notifier
from layerwatch.pipeline.policy import NotifySettings


def _post_server(record):
    """Start a local HTTP server; every POST is passed to ``record(handler, body)``, which returns the status.

    Returns the server (``server_address[1]`` is its port); shut it down with :func:`_stop`.
    """

    class H(BaseHTTPRequestHandler):
        def do_POST(self):  # noqa: N802
            body = self.rfile.read(int(self.headers["Content-Length"]))
            self.send_response(record(self, body))
            self.end_headers()

        def log_message(self, *a):
            pass

    srv = HTTPServer(("127.0.0.1", 0), H)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv


def _stop(srv):
    srv.shutdown()
    srv.server_close()


@pytest.fixture
def hook():
    got = []

    def record(handler, body):
        got.append(json.loads(body))
        return 500 if handler.path == "/fail" else 200

    srv = _post_server(record)
    yield f"http://127.0.0.1:{srv.server_address[1]}", got
    _stop(srv)


def test_webhook_posts_json_with_image_and_rate_limits(hook):
    url, got = hook
    now = [0.0]
    n = Notifier(NotifySettings(webhook_url=url + "/hook", min_interval_s=60), clock=lambda: now[0])
    assert n.notify("pause", "layer 5 failed", image=b"\x89PNGdata", data={"layer": 5})
    assert got[0]["title"] == "pause" and got[0]["data"] == {"layer": 5}
    assert base64.b64decode(got[0]["image_base64"]) == b"\x89PNGdata"
    now[0] = 30.0
    assert not n.notify("again", "x") and n.suppressed == 1 and len(got) == 1
    now[0] = 61.0
    assert n.notify("later", "y") and len(got) == 2


def test_webhook_failures_never_raise(hook):
    url, got = hook
    assert not Notifier(NotifySettings(webhook_url=url + "/fail", min_interval_s=0)).notify("t", "m")
    assert len(got) == 1
    assert not Notifier(NotifySettings(webhook_url="http://127.0.0.1:9/x", min_interval_s=0)).notify("t", "m")
    assert not Notifier(NotifySettings(webhook_url="http://127.0.0.1:9/x")).notify("t", "m", image="/nonexistent.png")


# -- the real Apprise package against a local HTTP server ---------------------------------------
# apprise's PGP helper imports the stdlib ``imghdr`` (deprecated in 3.11) when a notification is sent
_APPRISE_WARNINGS = pytest.mark.filterwarnings("ignore:'imghdr' is deprecated:DeprecationWarning")


@pytest.fixture
def inbox():
    """Local HTTP server recording (path, content type, raw body) of every POST."""
    got = []

    def record(handler, body):
        got.append((handler.path, handler.headers.get("Content-Type", ""), body))
        return 200

    srv = _post_server(record)
    yield f"127.0.0.1:{srv.server_address[1]}", got
    _stop(srv)


def _overlay_png(tmp_path):
    import cv2
    import numpy as np

    img = np.zeros((24, 32, 3), np.uint8)
    img[4:12, 8:20, 2] = 255  # a red failing region
    path = tmp_path / "overlay.png"
    assert cv2.imwrite(str(path), img)
    return path, img


@_APPRISE_WARNINGS
def test_apprise_json_delivers_title_message_type_and_overlay(inbox, tmp_path):
    pytest.importorskip("apprise")
    host, got = inbox
    path, _ = _overlay_png(tmp_path)
    n = Notifier(NotifySettings(apprise_urls=[f"json://{host}/alerts"], min_interval_s=0))
    assert n.notify("layerwatch: pause", "layer 16: 230 mm^2 outside the part", level="critical", image=path)
    assert len(got) == 1
    where, ctype, raw = got[0]
    body = json.loads(raw)
    assert where == "/alerts" and ctype.startswith("application/json")
    assert body["title"] == "layerwatch: pause" and body["message"] == "layer 16: 230 mm^2 outside the part"
    assert body["type"] == "failure"  # critical -> Apprise's failure type
    (att,) = body["attachments"]
    assert att["filename"] == "overlay.png" and att["mimetype"] == "image/png"
    assert base64.b64decode(att["base64"]) == path.read_bytes()


@_APPRISE_WARNINGS
def test_apprise_attaches_in_memory_overlays_and_survives_a_missing_file(inbox, tmp_path):
    import cv2

    pytest.importorskip("apprise")
    host, got = inbox
    _, img = _overlay_png(tmp_path)
    n = Notifier(NotifySettings(apprise_urls=[f"json://{host}/a"], min_interval_s=0))
    assert n.notify("t-array", "m", image=img)  # an overlay array, as the pipeline has it
    sent = json.loads(got[-1][2])["attachments"][0]
    decoded = cv2.imdecode(__import__("numpy").frombuffer(base64.b64decode(sent["base64"]), "uint8"), cv2.IMREAD_COLOR)
    assert (decoded == img).all()
    assert n.notify("t-bytes", "m", image=b"\xff\xd8\xff\xe0jpegdata")
    sent = json.loads(got[-1][2])["attachments"][0]
    assert sent["filename"] == "overlay.jpg" and base64.b64decode(sent["base64"]) == b"\xff\xd8\xff\xe0jpegdata"
    # the overlay file vanished: the alert still goes out, without an attachment
    assert n.notify("t-missing", "still sent", image=tmp_path / "gone.png")
    body = json.loads(got[-1][2])
    assert body["title"] == "t-missing" and body["attachments"] == []
    assert len(got) == 3


@_APPRISE_WARNINGS
def test_apprise_form_upload_carries_the_overlay_file(inbox, tmp_path):
    from email.parser import BytesParser
    from email.policy import HTTP

    pytest.importorskip("apprise")
    host, got = inbox
    path, _ = _overlay_png(tmp_path)
    n = Notifier(NotifySettings(apprise_urls=[f"form://{host}/form"], min_interval_s=0))
    assert n.notify("form title", "form message", level="warning", image=path)
    (_, ctype, raw) = got[0]
    assert ctype.startswith("multipart/form-data")
    msg = BytesParser(policy=HTTP).parsebytes(b"Content-Type: " + ctype.encode() + b"\r\n\r\n" + raw)
    parts = {p.get_param("name", header="content-disposition"): p for p in msg.iter_parts()}
    assert parts["title"].get_content().strip() == "form title"
    assert parts["message"].get_content().strip() == "form message"
    assert parts["type"].get_content().strip() == "warning"
    files = [p for p in parts.values() if p.get_filename() == "overlay.png"]
    assert len(files) == 1 and files[0].get_payload(decode=True) == path.read_bytes()


@_APPRISE_WARNINGS
def test_apprise_rate_limited_but_pauses_forced(inbox):
    pytest.importorskip("apprise")
    host, got = inbox
    now = [0.0]
    n = Notifier(NotifySettings(apprise_urls=[f"json://{host}/r"], min_interval_s=60), clock=lambda: now[0])
    assert n.notify("first", "a")
    now[0] = 20.0
    assert not n.notify("second", "b")  # inside the interval: dropped, nothing posted
    now[0] = 25.0
    assert n.notify("pause", "c", force=True)  # a pause is always told
    now[0] = 70.0
    assert not n.notify("third", "d")  # the forced one restarted the interval
    now[0] = 90.0
    assert n.notify("fourth", "e")
    assert [json.loads(b)["title"] for _, _, b in got] == ["first", "pause", "fourth"]
    assert n.sent == 3 and n.suppressed == 2


@_APPRISE_WARNINGS
def test_apprise_unreachable_or_bad_url_never_raises(caplog):
    pytest.importorskip("apprise")
    n = Notifier(NotifySettings(apprise_urls=["json://127.0.0.1:9/x"], min_interval_s=0))
    assert not n.notify("t", "m")
    assert not Notifier(NotifySettings(apprise_urls=["nosuchscheme://x"], min_interval_s=0)).notify("t", "m")
    assert "not understood" in caplog.text
