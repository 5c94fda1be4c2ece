"""The request-body cap holds for chunked bodies against a real uvicorn server (separate process).

A 1 GiB chunked upload (no Content-Length) must not raise the server's peak
resident memory (``VmHWM``) by more than 50 MB, must be answered 413 or cut
off, and must store nothing.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from layerwatch.storage.history import History
from layerwatch.web.settings import MAX_BODY, SETTINGS_KEY

httpx = pytest.importorskip("httpx")
pytest.importorskip("uvicorn")
pytestmark = [pytest.mark.slow, pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc")]

SERVER = textwrap.dedent(
    """
    import socket, sys
    import uvicorn
    from layerwatch.storage.history import History
    from layerwatch.web.app import create_app
    app = create_app(History(sys.argv[1]))
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.bind(("127.0.0.1", 0))
    print(sock.getsockname()[1], flush=True)
    uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off")).run(sockets=[sock])
    """
)
GIB = 1 << 30
CHUNK = 1 << 16


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def _read_answer(s: socket.socket) -> bytes:
    """Headers and body (``Content-Length`` of them) of one HTTP answer; the server may reset afterwards."""
    answer = b""
    while b"\r\n\r\n" not in answer or len(answer.split(b"\r\n\r\n", 1)[1]) < _length(answer):
        try:
            chunk = s.recv(4096)
        except ConnectionResetError:  # the server closed with our unread upload in its buffer
            break
        if not chunk:
            break
        answer += chunk
    return answer


def _length(answer: bytes) -> int:
    for line in answer.split(b"\r\n\r\n", 1)[0].split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            return int(line.split(b":", 1)[1])
    return 0


@pytest.fixture
def server(tmp_path):
    db = tmp_path / "history.db"
    proc = subprocess.Popen([sys.executable, "-c", SERVER, str(db)], stdout=subprocess.PIPE, text=True)
    client = None
    try:
        port = int(proc.stdout.readline())
        url = f"http://127.0.0.1:{port}"
        end = time.monotonic() + 60
        client = httpx.Client(base_url=url, timeout=60)
        while True:
            try:
                client.headers["X-CSRF-Token"] = client.get("/api/session").json()["csrf"]
                break
            except httpx.TransportError:
                assert time.monotonic() < end and proc.poll() is None, "server did not start"
                time.sleep(0.1)
        # warm the route up (imports, first validation) so the peak below is the upload's
        assert client.patch("/api/settings", json={"policy": {"pause_ratio": 0.2}}).status_code == 200
        yield proc, client, db
    finally:
        if client is not None:
            client.close()
        proc.terminate()
        proc.wait(10)
        proc.stdout.close()


def test_chunked_gigabyte_is_cut_at_the_cap(server):
    proc, client, db = server
    before = _peak_rss_mb(proc.pid)
    sent = 0

    def body():  # a generator: httpx sends it chunked, without Content-Length
        nonlocal sent
        block = b"9" * CHUNK
        while sent < GIB:
            sent += CHUNK
            yield block

    t0 = time.monotonic()
    try:
        r = client.patch("/api/settings", content=body(), headers={"content-type": "application/json"})
        status = r.status_code
    except httpx.TransportError:  # the server answered 413 and closed the connection mid-upload
        status = None
    grown = _peak_rss_mb(proc.pid) - before
    print(f"\nsent {sent / 2**20:.0f} MiB in {time.monotonic() - t0:.1f} s; answer {status}; "
          f"server peak RSS +{grown:.1f} MB")
    assert status in (413, None)
    assert grown <= 50, f"server peak memory grew {grown:.0f} MB for a chunked 1 GiB upload"
    assert proc.poll() is None  # still serving
    assert client.get("/api/settings").json()["policy"]["pause_ratio"] == 0.2
    with History(db) as h:
        assert h.setting(SETTINGS_KEY)["policy"]["pause_ratio"] == 0.2  # nothing of the upload stored


def test_chunked_body_just_over_the_cap_gets_413(server):
    proc, client, _ = server
    host, port = client.base_url.host, client.base_url.port
    cookie = "; ".join(f"{k}={v}" for k, v in client.cookies.items())
    with socket.create_connection((host, port), timeout=30) as s:
        s.sendall((f"PATCH /api/settings HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
                   f"Transfer-Encoding: chunked\r\nX-CSRF-Token: {client.headers['X-CSRF-Token']}\r\n"
                   f"Cookie: {cookie}\r\n\r\n").encode())
        chunk = b"%x\r\n%s\r\n" % (CHUNK, b"9" * CHUNK)
        for _ in range(MAX_BODY // CHUNK + 1):  # one chunk over the cap, body left unfinished
            s.sendall(chunk)
        answer = _read_answer(s)
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    assert b"larger than 1 MiB" in answer
