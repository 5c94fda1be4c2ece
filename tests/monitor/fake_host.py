"""A fake printer host on 127.0.0.1 that answers like OctoPrint or Moonraker, or breaks on request.

``FakeHost.fault = "<kind>"`` makes every following request get that kind of
bad reply (:data:`HTTP_FAULTS`); ``fault = None`` answers properly again;
:meth:`FakeHost.down` closes the port (connection refused) and :meth:`up`
reopens it on the same port. Used by ``test_fault_injection.py``.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

#: the good replies of a printing job
GOOD = {
    "octoprint": {"state": "Printing", "job": {"file": {"name": "part.gcode"}}, "progress": {"completion": 42.0}},
    "moonraker": {"result": {"status": {"print_stats": {"state": "printing", "filename": "part.gcode"},
                                        "gcode_move": {"gcode_position": [10.0, 20.0, 1.2, 300.0]},
                                        "virtual_sdcard": {"progress": 0.42},
                                        "webhooks": {"state": "ready", "state_message": "Printer is ready"}}}},
}
FINISHED = {
    "octoprint": {"state": "Operational", "job": {"file": {"name": "part.gcode"}}, "progress": {"completion": 100}},
    "moonraker": {"result": {"status": {"print_stats": {"state": "complete", "filename": "part.gcode"}}}},
}

_HTML = b"<!doctype html><html><head><title>Login</title></head><body><form>password</form></body></html>"


def _wrong_types(host: str) -> bytes:
    if host == "octoprint":
        return json.dumps({"state": 7, "job": [], "progress": "half"}).encode()
    return json.dumps({"result": {"status": {"print_stats": ["printing"], "gcode_move": {"gcode_position": "x"}}}}).encode()


def _nulls(host: str) -> bytes:
    if host == "octoprint":
        return json.dumps({"state": None, "job": None, "progress": None}).encode()
    return json.dumps({"result": None}).encode()


def _nan(host: str) -> bytes:
    if host == "octoprint":
        return b'{"state": "Printing", "job": {"file": {"name": "a"}}, "progress": {"completion": NaN}}'
    return (b'{"result": {"status": {"print_stats": {"state": "printing"}, '
            b'"virtual_sdcard": {"progress": NaN}, "gcode_move": {"gcode_position": [0, 0, Infinity]}}}}')


def _out_of_range(host: str) -> bytes:
    if host == "octoprint":
        return json.dumps({"state": "Printing", "progress": {"completion": 1e308}}).encode()
    return json.dumps({"result": {"status": {"virtual_sdcard": {"progress": -3.5}}}}).encode()


def _top_array(host: str) -> bytes:
    return b"[1, 2, 3]"


def _no_result(host: str) -> bytes:
    return json.dumps({"error": None, "state": {"text": "Printing"}}).encode()


#: kind -> (status, content type, body or body(host), how the body is sent)
HTTP_FAULTS: dict[str, tuple] = {
    "html_200": (200, "text/html", _HTML, "plain"),
    "truncated_json": (200, "application/json", b'{"state": "Printing", "job": {"file": {"na', "plain"),
    "wrong_types": (200, "application/json", _wrong_types, "plain"),
    "null_fields": (200, "application/json", _nulls, "plain"),
    "nan_numbers": (200, "application/json", _nan, "plain"),
    "out_of_range_numbers": (200, "application/json", _out_of_range, "plain"),
    "json_array": (200, "application/json", _top_array, "plain"),
    "missing_fields": (200, "application/json", _no_result, "plain"),
    "empty_body": (200, "application/json", b"", "plain"),
    "not_utf8": (200, "application/json", b'{"state": "\xff\xfe\xfa"}', "plain"),
    "deep_nesting": (200, "application/json", b"[" * 200_000 + b"]" * 200_000, "plain"),
    "text_plain_json": (200, "text/plain", lambda h: json.dumps(GOOD[h]).encode(), "plain"),
    "huge_body": (200, "application/json", b"[" + b"0," * 3_000_000 + b"0]", "plain"),
    "huge_chunked": (200, "application/json", None, "chunked_forever"),
    "http_500": (500, "text/plain", b"Internal Server Error", "plain"),
    "http_404": (404, "text/html", b"<h1>Not Found</h1>", "plain"),
    "http_502_proxy": (502, "text/html", b"<html><body>502 Bad Gateway nginx</body></html>", "plain"),
    "http_503": (503, "application/json", b'{"error": {"code": 503, "message": "Klippy Host not connected"}}', "plain"),
    "http_401": (401, "application/json", b'{"error": "Invalid API key"}', "plain"),
    "timeout": (200, "application/json", None, "hang"),
    "reset_mid_body": (200, "application/json", None, "reset"),
    "close_without_reply": (200, "application/json", None, "close"),
    "garbage_status_line": (200, "application/json", None, "garbage"),
}


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    host: FakeHost  # set on the subclass

    def log_message(self, *a):
        pass

    def setup(self):
        super().setup()
        self.host.conns.add(self.connection)  # down() closes kept-alive connections too

    def finish(self):
        self.host.conns.discard(self.connection)
        try:
            super().finish()
        except OSError:
            pass

    def _answer(self):
        length = int(self.headers.get("Content-Length") or 0)
        if length:
            self.rfile.read(length)
        h = self.host
        h.requests += 1
        if h.fault is None:
            return self._send(200, "application/json", json.dumps(h.reply).encode())
        if self.command != "GET" and h.fault_only_gets:
            return self._send(204, "application/json", b"")
        code, ctype, body, how = HTTP_FAULTS[h.fault]
        if how == "hang":
            h.changed.wait(30)  # a slow host: it answers once it is back (or never)
            return self._answer_after_hang()
        if how in ("reset", "close", "garbage"):
            if how == "reset":
                self.wfile.write(b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: 5000\r\n\r\n{\"st")
            elif how == "garbage":
                self.wfile.write(b"\x16\x03\x01 not http at all\r\n\r\n")
            self.wfile.flush()
            self.connection.shutdown(socket.SHUT_RDWR)
            self.close_connection = True
            return None
        if how == "chunked_forever":
            self.send_response(200)
            self.send_header("Content-Type", ctype)
            self.send_header("Transfer-Encoding", "chunked")
            self.end_headers()
            chunk = b"[" + b"0," * 32_000
            try:
                for _ in range(2000):  # up to 128 MB, unless the client hangs up first
                    self.wfile.write(b"%x\r\n%s\r\n" % (len(chunk), chunk))
            except OSError:
                pass
            self.close_connection = True
            return None
        data = body(h.name) if callable(body) else body
        return self._send(code, ctype, data)

    def _answer_after_hang(self):
        if self.host.fault is None:
            return self._send(200, "application/json", json.dumps(self.host.reply).encode())
        self.close_connection = True
        return None

    def _send(self, code, ctype, data):
        try:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)
        except OSError:
            self.close_connection = True

    do_GET = do_POST = _answer


class FakeHost:
    """One fake OctoPrint (``name="octoprint"``) or Moonraker host.

    Attributes
    ----------
    fault : str or None
        Kind of bad reply (a key of :data:`HTTP_FAULTS`), None for good replies.
    reply : dict
        The good reply (``GOOD[name]``; ``FINISHED[name]`` ends a monitor's run).
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self.fault: str | None = None
        self.fault_only_gets = True  # commands (pause) answer 204 during a fault: the test counts them
        self.reply = GOOD[name]
        self.requests = 0
        self.conns: set[socket.socket] = set()
        self.changed = threading.Event()
        self.port = 0
        self._srv: ThreadingHTTPServer | None = None
        self.up()

    @property
    def hostport(self) -> str:
        return f"127.0.0.1:{self.port}"

    def set_fault(self, kind: str | None) -> float:
        """Switch to ``kind`` (None: good replies); returns the switch time (monotonic)."""
        self.fault = kind
        self.changed.set()
        self.changed = threading.Event()
        return time.monotonic()

    def up(self) -> float:
        handler = type("H", (_Handler,), {"host": self})
        self._srv = ThreadingHTTPServer(("127.0.0.1", self.port), handler)
        self._srv.daemon_threads = True
        self.port = self._srv.server_address[1]
        threading.Thread(target=self._srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
        return time.monotonic()

    def down(self) -> None:
        """Close the port and every open connection: connections are refused until :meth:`up`."""
        if self._srv is not None:
            self._srv.shutdown()
            self._srv.server_close()
            self._srv = None
        for conn in list(self.conns):
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def close(self) -> None:
        self.set_fault(None)
        self.down()
