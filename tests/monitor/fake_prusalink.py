"""A fake PrusaLink on 127.0.0.1: the v1 API behind real HTTP digest auth (RFC 7616, MD5, qop=auth).

It prints one job whose Z the test sets (``FakePrusaLink.z``), answers ``/api/v1/status``,
``/api/v1/job``, ``PUT /api/v1/job/{id}/pause|resume``, ``DELETE /api/v1/job/{id}`` and
``/api/v1/cameras/snap`` as the PrusaLink OpenAPI says (409 for a command in the wrong state,
204 without a job or a snapshot), and breaks on request (:data:`FAULTS`) like ``fake_host``.
"""

from __future__ import annotations

import hashlib
import json
import re
import secrets
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np

REALM = "Printer API"

#: kind -> (status, content type, body); "hang" waits until the fault is cleared, "reset" cuts the body
FAULTS: dict[str, tuple] = {
    "html_200": (200, "text/html", b"<!doctype html><html><body>PrusaLink login</body></html>"),
    "truncated_json": (200, "application/json", b'{"printer": {"state": "PRIN'),
    "wrong_types": (200, "application/json", b'{"printer": {"state": 7, "axis_z": "high"}, "job": {"id": "x"}}'),
    "nan_numbers": (200, "application/json", b'{"printer": {"state": "PRINTING", "axis_z": NaN}, "job": {"id": 1}}'),
    "out_of_range": (200, "application/json", b'{"printer": {"state": "PRINTING", "axis_z": 1.0}, '
                                              b'"job": {"id": 1, "progress": 250}}'),
    "json_array": (200, "application/json", b"[1, 2, 3]"),
    "missing_printer": (200, "application/json", b'{"job": {"id": 1}}'),
    "empty_body": (200, "application/json", b""),
    "huge_body": (200, "application/json", b"[" + b"0," * 3_000_000 + b"0]"),
    "http_500": (500, "text/plain", b"Internal Server Error"),
    "http_401": (401, "application/json", b'{"title": "Unauthorized"}'),
    "timeout": (200, "application/json", "hang"),
    "reset_mid_body": (200, "application/json", "reset"),
}


def _md5(text: str) -> str:
    return hashlib.md5(text.encode()).hexdigest()  # noqa: S324 - RFC 7616 digest, what PrusaLink speaks


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    fake: FakePrusaLink

    def log_message(self, *a):
        pass

    def setup(self):
        super().setup()
        self.fake.conns.add(self.connection)

    def finish(self):
        self.fake.conns.discard(self.connection)
        try:
            super().finish()
        except OSError:
            pass

    def _authorised(self) -> bool:
        """Check the Authorization header as a digest server does (nonce, realm, uri, response)."""
        head = self.headers.get("Authorization", "")
        if not head.startswith("Digest "):
            return False
        f = dict(re.findall(r'(\w+)="?([^",]*)"?', head[7:]))
        if f.get("nonce") not in self.fake.nonces or f.get("realm") != REALM or f.get("uri") != self.path:
            return False
        ha1 = _md5(f"{f.get('username')}:{REALM}:{self.fake.password}")
        ha2 = _md5(f"{self.command}:{f['uri']}")
        want = _md5(f"{ha1}:{f['nonce']}:{f.get('nc')}:{f.get('cnonce')}:{f.get('qop')}:{ha2}")
        return f.get("username") == self.fake.user and f.get("response") == want

    def _challenge(self):
        nonce = secrets.token_hex(16)
        self.fake.nonces.add(nonce)
        self.fake.refused += 1
        self._send(401, "application/json", b'{"title": "Unauthorized"}',
                   {"WWW-Authenticate": f'Digest realm="{REALM}", nonce="{nonce}", qop="auth", algorithm=MD5'})

    def _answer(self):
        length = int(self.headers.get("Content-Length") or 0)
        if length:
            self.rfile.read(length)
        if not self._authorised():
            return self._challenge()
        fk = self.fake
        fk.requests.append((self.command, self.path))
        if fk.fault is not None and self.command == "GET" and self.path == "/api/v1/status":
            return self._fault(*FAULTS[fk.fault])
        code, ctype, body = fk.route(self.command, self.path)
        return self._send(code, ctype, body)

    def _fault(self, code, ctype, body):
        if body == "hang":
            self.fake.changed.wait(30)
            self.close_connection = True
            return None
        if body == "reset":
            self.wfile.write(b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: 900\r\n\r\n{\"pr")
            self.wfile.flush()
            self.connection.shutdown(socket.SHUT_RDWR)
            self.close_connection = True
            return None
        return self._send(code, ctype, body)

    def _send(self, code, ctype, data, headers=None):
        try:
            self.send_response(code)
            for k, v in (headers or {}).items():
                self.send_header(k, v)
            if code != 204:
                self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)
        except OSError:
            self.close_connection = True

    do_GET = do_PUT = do_DELETE = do_POST = _answer


class FakePrusaLink:
    """One fake printer running job ``job_id``; the test moves ``z`` and reads ``state``."""

    def __init__(self, user: str = "maker", password: str = "s3cret-PL") -> None:
        self.user, self.password = user, password
        self.state = "PRINTING"
        self.job_id: int | None = 7
        self.z = 0.2
        self.progress = 10.0
        self.snapshot: bytes | None = cv2.imencode(".png", np.full((48, 64, 3), 90, np.uint8))[1].tobytes()
        self.fault: str | None = None
        self.changed = threading.Event()
        self.nonces: set[str] = set()
        self.requests: list[tuple[str, str]] = []
        self.refused = 0
        self.conns: set[socket.socket] = set()
        handler = type("H", (_Handler,), {"fake": self})
        self._srv = ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self._srv.daemon_threads = True
        self.port = self._srv.server_address[1]
        threading.Thread(target=self._srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()

    @property
    def url(self) -> str:
        return f"prusalink://127.0.0.1:{self.port}?user={self.user}"

    def set_fault(self, kind: str | None) -> None:
        self.fault = kind
        self.changed.set()
        self.changed = threading.Event()

    def route(self, method: str, path: str) -> tuple[int, str, bytes]:
        """The API's answer to one authenticated request."""
        js = "application/json"
        if method == "GET" and path == "/api/v1/status":
            job = {} if self.job_id is None else {"job": {"id": self.job_id, "progress": self.progress}}
            return 200, js, json.dumps({"printer": {"state": self.state, "axis_z": self.z, "temp_bed": 60.0},
                                        **job}).encode()
        if method == "GET" and path == "/api/v1/job":
            if self.job_id is None:
                return 204, js, b""
            return 200, js, json.dumps({"id": self.job_id, "state": self.state, "progress": self.progress,
                                        "file": {"name": "PART~1.BGC", "display_name": "part.bgcode",
                                                 "path": "/usb"}}).encode()
        if method == "GET" and path == "/api/v1/cameras/snap":
            return (204, js, b"") if self.snapshot is None else (200, "image/png", self.snapshot)
        m = re.fullmatch(r"/api/v1/job/(\d+)(?:/(pause|resume))?", path)
        if m is None or self.job_id is None or int(m[1]) != self.job_id:
            return 404, js, b'{"title": "Not Found"}'
        wanted = {("PUT", "pause"): ("PRINTING", "PAUSED"), ("PUT", "resume"): ("PAUSED", "PRINTING"),
                  ("DELETE", None): (None, "STOPPED")}.get((method, m[2]))
        if wanted is None:
            return 405, js, b'{"title": "Method Not Allowed"}'
        before, after = wanted
        if before is not None and self.state != before or self.state in ("FINISHED", "STOPPED"):
            return 409, js, b'{"title": "Conflict", "message": "Job is not in a state for this"}'
        self.state = after
        return 204, js, b""

    def close(self) -> None:
        self.set_fault(None)
        self._srv.shutdown()
        self._srv.server_close()
        for conn in list(self.conns):
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
