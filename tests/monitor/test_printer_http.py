"""The shared HTTP error mapping of the printer connectors (base.http_request).

A local http.server answers with the status/body each test asks for; both
connectors must turn them into one-line PrinterErrors that name the fix.
"""

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import pytest

from layerwatch.errors import PrinterError
from layerwatch.monitor.printers.base import error_detail, http_request
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter
from layerwatch.monitor.printers.octoprint import OctoPrintPrinter

TRACEBACK_BODY = json.dumps({"error": {"code": 503, "message": "Klippy Host not connected",
                                       "traceback": "Traceback (most recent call last):\n  File x"}})


class _Handler(BaseHTTPRequestHandler):
    reply = (200, "application/json", "{}")

    def _answer(self):
        code, ctype, body = type(self).reply
        data = body.encode()
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    do_GET = do_POST = _answer

    def log_message(self, *a):
        pass


@pytest.fixture
def server():
    srv = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    yield srv, f"127.0.0.1:{srv.server_address[1]}"
    srv.shutdown()
    srv.server_close()


def _set(code, body, ctype="application/json"):
    _Handler.reply = (code, ctype, body)


def test_error_detail_keeps_message_drops_traceback_and_html():
    assert error_detail(TRACEBACK_BODY) == "Klippy Host not connected"
    assert error_detail('{"error": "Printer is not operational"}') == "Printer is not operational"
    assert error_detail("<html><body><h1>Forbidden</h1>\n<p>no</p></body></html>") == "Forbidden no"
    assert error_detail("") == "(empty body)"
    assert len(error_detail("x" * 1000)) == 160


def test_moonraker_mapping(server):
    _, hostport = server
    with MoonrakerPrinter(f"moonraker://{hostport}", push=False) as p:
        _set(503, TRACEBACK_BODY)
        with pytest.raises(PrinterError) as e:
            p.status()
        msg = str(e.value)
        assert "Klippy Host not connected" in msg and "Traceback" not in msg and "FIRMWARE_RESTART" in msg
        _set(401, '{"error": {"code": 401, "message": "Unauthorized"}}')
        with pytest.raises(PrinterError, match=r"refused the request \(HTTP 401: Unauthorized\); set LAYERWATCH_MOONRAKER_KEY"):
            p.pause()
        _set(500, "boom")
        with pytest.raises(PrinterError, match=r"Moonraker POST /printer/print/cancel failed with HTTP 500: boom"):
            p.cancel()
        _set(200, '{"result": "ok"}')
        p.resume()  # no error


def test_octoprint_mapping(server):
    _, hostport = server
    with OctoPrintPrinter(f"octoprint://{hostport}?key=K", push=False) as p:
        _set(403, "<html><h1>Forbidden</h1></html>", "text/html")
        with pytest.raises(PrinterError, match=r"OctoPrint at .* refused the API key \(HTTP 403: Forbidden\); copy the key"):
            p.status()
        _set(409, '{"error": "Printer is not operational"}')
        with pytest.raises(PrinterError, match=r"refused POST /api/job \(HTTP 409: Printer is not operational\); the printer is not connected"):
            p.pause()
        _set(404, "not here", "text/plain")
        with pytest.raises(PrinterError, match="OctoPrint POST /api/printer/command failed with HTTP 404: not here"):
            p.send_gcode("M105")


def test_unreachable_names_host_and_fix():
    with httpx.Client(base_url="http://127.0.0.1:9", timeout=1) as c, pytest.raises(PrinterError) as e:
        http_request(c, "GET", "/x", printer="Moonraker", credential="the request", auth_hint="-")
    assert str(e.value) == ("Moonraker at http://127.0.0.1:9 unreachable (ConnectError); "
                            "check host, port and that it runs.")


def test_octoprint_transient_states_and_resume_while_pausing(server):
    _, hostport = server
    with OctoPrintPrinter(f"octoprint://{hostport}?key=K", push=False) as p:
        for octo, ours in [("Pausing", "pausing"), ("Paused", "paused"), ("Resuming", "resuming"),
                           ("Cancelling", "cancelling"), ("Printing from SD", "printing"),
                           ("Offline after error", "offline"), ("Opening serial connection", "offline")]:
            _set(200, json.dumps({"state": octo, "job": {"file": {"name": "a.gcode"}}, "progress": {}}))
            assert p.status().state == ours, octo
        _set(200, json.dumps({"state": "Pausing", "job": {}, "progress": {}}))
        with pytest.raises(PrinterError, match="still pausing"):
            p.resume()
