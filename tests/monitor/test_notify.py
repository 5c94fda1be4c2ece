import base64
import json
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer

import pytest

from layerwatch.monitor.notify import Notifier
from layerwatch.monitor.settings import NotifySettings


@pytest.fixture
def hook():
    got = []

    class H(BaseHTTPRequestHandler):
        def do_POST(self):  # noqa: N802
            n = int(self.headers["Content-Length"])
            got.append(json.loads(self.rfile.read(n)))
            self.send_response(500 if self.path == "/fail" else 200)
            self.end_headers()

        def log_message(self, *a):
            pass

    srv = HTTPServer(("127.0.0.1", 0), H)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}", got
    srv.shutdown()
    srv.server_close()


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
