"""The camera of Bambu Lab P1 and A1 printers in LAN mode: JPEG frames over TLS on TCP port 6000.

Protocol (as the printers speak it; community-documented, the one BambuStudio's LAN live view uses):

- the client opens TLS to port 6000 (the printer's self-signed certificate) and sends an
  80-byte login: the little-endian words ``0x40``, ``0x3000``, ``0``, ``0``, then the user
  ``bblp`` and the access code, each NUL-padded to 32 bytes;
- the printer then streams frames, each a 16-byte header whose first 4 bytes are the JPEG's
  length (little-endian), followed by the JPEG (``FF D8`` ... ``FF D9``), about one per second.

:meth:`BambuCamera.grab` opens a connection, logs in, reads one frame and closes; a refused
login (the printer just closes), a time-out, an implausible length or bytes that are not a
JPEG are a :class:`~layerwatch.errors.CameraError` naming the fix.

X1 printers instead serve RTSP over TLS (``rtsps://bblp:<code>@<host>:322/streaming/live/1``,
with "LAN mode liveview" switched on), which this module does not read: it needs an RTSP
client (ffmpeg). A go2rtc or ffmpeg relay that turns it into an MJPEG or snapshot URL works
with ``--camera http://...``.
"""

from __future__ import annotations

import math
import socket
import ssl
import struct
from pathlib import Path
from typing import Any

import numpy as np

from layerwatch.errors import CameraError, ConfigError
from layerwatch.monitor.cameras import Camera, decode_image
from layerwatch.monitor.mqtt import tls_context

__all__ = ["BambuCamera", "login_packet", "CAMERA_PORT", "MAX_FRAME_BYTES"]

#: TCP port of the P1/A1 camera stream
CAMERA_PORT = 6000

#: largest frame accepted, bytes (a 1280x720 JPEG is ~100 KB)
MAX_FRAME_BYTES = 8 << 20


def login_packet(access_code: str, user: str = "bblp") -> bytes:
    """The 80-byte login the printer expects first.

    Raises
    ------
    ConfigError
        A user or access code longer than 32 bytes or not printable ASCII.
    """
    parts = []
    for what, text in (("user", user), ("access code", access_code)):
        raw = text.encode("ascii", "replace")
        if not 0 < len(raw) <= 32 or not text.isascii() or not text.isprintable():
            raise ConfigError(f"Bambu camera {what} must be 1-32 printable ASCII characters; copy it from the printer.")
        parts.append(raw.ljust(32, b"\0"))
    return struct.pack("<IIII", 0x40, 0x3000, 0, 0) + b"".join(parts)


def _read_exact(conn: ssl.SSLSocket, n: int, where: str, what: str) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = conn.recv(min(n - len(buf), 1 << 16))
        if not chunk:
            raise CameraError(f"{where} closed the stream after {len(buf)} of {n} bytes of {what}; "
                              "check the access code and that LAN mode liveview is on.")
        buf += chunk
    return bytes(buf)


class BambuCamera(Camera):
    """One JPEG from a P1/A1 printer's camera per :meth:`grab`.

    Parameters
    ----------
    host : str
        The printer's address.
    access_code : str
        LAN access code (the MQTT password).
    port : int
        Camera port (6000).
    ca_file : str or Path, optional
        CA of the printer's certificate (verified when given; not its host name, which is the serial).
    timeout_s : float
        Connect and read time-out, s.
    **kw
        :class:`~layerwatch.monitor.cameras.Camera` options (retries, settle_s...).
    """

    def __init__(self, host: str, access_code: str, *, port: int = CAMERA_PORT, ca_file: str | Path | None = None,
                 timeout_s: float = 5.0, **kw: Any) -> None:
        super().__init__(**kw)
        if not (math.isfinite(timeout_s) and 0 < timeout_s <= 120):
            raise ConfigError("Bambu camera timeout must be 0-120 s.")
        if not 0 < int(port) < 65536:
            raise ConfigError("Bambu camera port must be 1-65535.")
        self.host, self.port, self.timeout_s = host, int(port), float(timeout_s)
        self._login = login_packet(access_code)
        self._tls = tls_context(ca_file)
        self.where = f"Bambu camera {host}:{self.port}"

    def _read(self) -> np.ndarray:
        try:
            with socket.create_connection((self.host, self.port), timeout=self.timeout_s) as raw, \
                    self._tls.wrap_socket(raw, server_hostname=self.host) as conn:
                conn.sendall(self._login)
                head = _read_exact(conn, 16, self.where, "a frame header")
                size = struct.unpack_from("<I", head)[0]
                if not 4 <= size <= MAX_FRAME_BYTES:
                    raise CameraError(f"{self.where} announced a {size}-byte frame; is port {self.port} the camera "
                                      "of a P1/A1 printer?")
                data = _read_exact(conn, size, self.where, "a frame")
        except TimeoutError:
            raise CameraError(f"{self.where} sent no frame within {self.timeout_s:g} s; check that the printer is on "
                              "and LAN mode liveview is enabled.") from None
        except (OSError, ssl.SSLError) as exc:
            raise CameraError(f"{self.where} unreachable ({type(exc).__name__}: {exc}); check the address, "
                              "and ?ca= if given.") from None
        if not (data.startswith(b"\xff\xd8") and data.rstrip(b"\0").endswith(b"\xff\xd9")):
            raise CameraError(f"{self.where} sent {size} bytes that are not a JPEG; is this a P1/A1 printer's camera?")
        return decode_image(data, self.where)
