"""The P1/A1 camera reader against a fake printer camera: TLS on a free port, the 80-byte login, framed JPEGs.

The fake checks the login (user ``bblp``, the access code, the header words) and closes the
connection on a wrong one, as the printer does; it can also send a truncated frame, an absurd
length, bytes that are not a JPEG, or nothing at all. Each is one :class:`CameraError`.
"""

from __future__ import annotations

import shutil
import socket
import ssl
import struct
import subprocess
import threading

import cv2
import numpy as np
import pytest

from layerwatch.errors import CameraError, ConfigError
from layerwatch.monitor.printers.bambu_camera import BambuCamera, login_packet

CODE = "12345678"
FRAME = cv2.imencode(".jpg", np.tile(np.arange(64, dtype=np.uint8), (48, 1))[:, :, None].repeat(3, 2))[1].tobytes()


class FakeCamera:
    """A P1/A1 camera port; ``mode`` picks what it sends after a good login."""

    def __init__(self, folder):
        if shutil.which("openssl") is None:
            pytest.skip("openssl CLI not installed (apt-get install openssl)")
        self.cert, key = folder / "cam.crt", folder / "cam.key"
        subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj",
                        "/CN=01P00A000000000", "-keyout", str(key), "-out", str(self.cert)], check=True,
                       capture_output=True)
        self.ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        self.ctx.load_cert_chain(self.cert, key)
        self.mode = "good"
        self.logins: list[bytes] = []
        self.release = threading.Event()
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                raw, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._one, args=(raw,), daemon=True).start()

    def _one(self, raw):
        try:
            with self.ctx.wrap_socket(raw, server_side=True) as conn:
                login = b""
                while len(login) < 80:
                    chunk = conn.recv(80 - len(login))
                    if not chunk:
                        return
                    login += chunk
                self.logins.append(login)
                if login != login_packet(CODE):
                    return  # the printer hangs up on a wrong login
                head = lambda n: struct.pack("<I", n) + b"\0" * 4 + b"\1" + b"\0" * 7  # noqa: E731
                if self.mode == "good":
                    conn.sendall(head(len(FRAME)) + FRAME + head(len(FRAME)) + FRAME)
                elif self.mode == "truncated":
                    conn.sendall(head(len(FRAME)) + FRAME[: len(FRAME) // 2])
                elif self.mode == "huge":
                    conn.sendall(head(200_000_000) + FRAME)
                elif self.mode == "not_jpeg":
                    conn.sendall(head(9) + b"<!doctype")
                elif self.mode == "silent":
                    self.release.wait(5)
        except (OSError, ssl.SSLError):
            pass

    def close(self):
        self.release.set()
        self.sock.close()


@pytest.fixture(scope="module")
def camera_port(tmp_path_factory):
    c = FakeCamera(tmp_path_factory.mktemp("bambu-camera"))
    yield c
    c.close()


@pytest.fixture
def cam(camera_port):
    camera_port.mode = "good"
    camera_port.logins.clear()
    return camera_port


def test_login_packet_layout():
    pkt = login_packet("abcd")
    assert len(pkt) == 80 and pkt[:16] == bytes.fromhex("40000000003000000000000000000000")
    assert pkt[16:48] == b"bblp".ljust(32, b"\0") and pkt[48:80] == b"abcd".ljust(32, b"\0")
    with pytest.raises(ConfigError):
        login_packet("x" * 33)


def test_grabs_a_frame_with_the_printers_ca(cam):
    img = BambuCamera("127.0.0.1", CODE, port=cam.port, ca_file=cam.cert, retries=0).grab()
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    assert cam.logins == [login_packet(CODE)]


@pytest.mark.parametrize("mode, code, match", [
    ("good", "wrong", "closed the stream.*access code"),
    ("truncated", CODE, "closed the stream after"),
    ("huge", CODE, "200000000-byte frame"),
    ("not_jpeg", CODE, "not a JPEG"),
    ("silent", CODE, "no frame within 0.5 s"),
])
def test_bad_streams_are_camera_errors(cam, mode, code, match):
    cam.mode = mode
    with pytest.raises(CameraError, match=match):
        BambuCamera("127.0.0.1", code, port=cam.port, timeout_s=0.5, retries=0).grab()


def test_certificate_of_another_ca_is_refused(cam, tmp_path):
    other = tmp_path / "other.crt"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=x",
                    "-keyout", str(tmp_path / "other.key"), "-out", str(other)], check=True, capture_output=True)
    with pytest.raises(CameraError, match="unreachable.*SSL"):
        BambuCamera("127.0.0.1", CODE, port=cam.port, ca_file=other, retries=0).grab()
    assert cam.logins == []  # the access code never left for an unverified peer
