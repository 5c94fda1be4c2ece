import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np
import pytest

from layerwatch.errors import CameraError
from layerwatch.monitor.cameras import (
    Camera,
    FolderCamera,
    MjpegCamera,
    SimCamera,
    SnapshotCamera,
    frame_digest,
    open_camera,
)


def _jpeg(seed):
    img = np.random.default_rng(seed).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    return cv2.imencode(".png", img)[1].tobytes(), img


@pytest.fixture(scope="module")
def server():
    state = {"n": 0}

    class H(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802
            if self.path.startswith("/snap"):
                state["n"] += 1
                body, ctype = _jpeg(state["n"])[0], "image/png"
            elif self.path == "/same":
                body, ctype = _jpeg(0)[0], "image/png"
            elif self.path == "/html":
                body, ctype = b"<!DOCTYPE html><html>login</html>", "text/html"
            elif self.path == "/tiny":
                body, ctype = cv2.imencode(".png", np.zeros((1, 1, 3), np.uint8))[1].tobytes(), "image/png"
            elif self.path == "/stream":
                jpg = cv2.imencode(".jpg", np.full((40, 60, 3), 128, np.uint8))[1].tobytes()
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                for _ in range(2):
                    self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\n\r\n" + jpg + b"\r\n")
                return
            else:
                self.send_response(404)
                self.end_headers()
                return
            self.send_response(200)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *a):
            pass

    srv = ThreadingHTTPServer(("127.0.0.1", 0), H)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{srv.server_address[1]}"
    srv.shutdown()
    srv.server_close()


def test_snapshot_ok_and_errors(server):
    cam = SnapshotCamera(server + "/snap?action=snapshot", sleep=lambda s: None)
    a, b = cam.grab(), cam.grab()
    assert a.shape == (48, 64, 3) and a.dtype == np.uint8 and not np.array_equal(a, b)
    same = SnapshotCamera(server + "/same", sleep=lambda s: None)
    same.grab()
    with pytest.raises(CameraError, match="same frame twice"):
        same.grab()
    with pytest.raises(CameraError, match="web page"):
        SnapshotCamera(server + "/html", sleep=lambda s: None).grab()
    with pytest.raises(CameraError, match="1x1"):
        SnapshotCamera(server + "/tiny", sleep=lambda s: None).grab()
    with pytest.raises(CameraError, match="HTTP 404"):
        SnapshotCamera(server + "/nothing", retries=1, sleep=lambda s: None).grab()
    with pytest.raises(CameraError, match="unreachable"):
        SnapshotCamera("http://127.0.0.1:9/x", retries=0, timeout_s=1).grab()


def test_mjpeg_stream(server):
    img = MjpegCamera(server + "/stream").grab()
    assert img.shape == (40, 60, 3) and abs(int(img.mean()) - 128) <= 2
    assert isinstance(open_camera(server + "/?action=stream"), MjpegCamera)


def test_folder_and_sim(tmp_path):
    for i in range(2):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), _jpeg(10 + i)[1])
    cam = open_camera(f"file:{tmp_path}")
    assert isinstance(cam, FolderCamera)
    assert np.array_equal(cam.grab(), _jpeg(10)[1])
    assert np.array_equal(cam.grab(), _jpeg(11)[1])
    with pytest.raises(CameraError, match="no new image"):
        cam.grab()
    sim = SimCamera(lambda layer: np.full((32, 32, 3), layer, np.uint8))
    sim.set_layer(7)
    assert sim.grab()[0, 0, 0] == 7
    with pytest.raises(CameraError, match="unknown camera"):
        open_camera("ftp://x")


def test_frame_digest_tells_one_changed_pixel_and_is_skipped_without_the_stale_check():
    img = np.random.default_rng(2).integers(0, 256, (1080, 1920, 3), dtype=np.uint8)
    other = img.copy()
    other[540, 960, 1] ^= 1  # one bit of one pixel
    assert frame_digest(img) == frame_digest(img.copy()) != frame_digest(other)
    assert frame_digest(img[:, ::2]) == frame_digest(np.ascontiguousarray(img[:, ::2]))  # a strided view as its copy
    frames = iter([img, img])
    cam = SimCamera(lambda i: next(frames))
    assert cam.stale_check is False
    cam.grab(), cam.grab()
    assert cam._stale.last is None  # nothing hashed when the check is off


def test_the_stale_check_of_a_camera_that_sends_files_reads_the_file():
    """A snapshot camera's frames are fingerprinted as the files it sent (0.3 MB, not 6 MB of pixels): the same
    file twice is a frozen stream; the same pixels in another file (a comment added) are left to the gate."""
    from layerwatch.monitor.cameras import file_digest

    img = np.random.default_rng(3).integers(0, 256, (64, 80, 3), dtype=np.uint8)
    jpg = cv2.imencode(".jpg", img)[1].tobytes()
    commented = jpg[:2] + b"\xff\xfe\x00\x05abc" + jpg[2:]  # a COM segment: other bytes, the same pixels

    class Files(Camera):
        def __init__(self, files):
            super().__init__(retries=0)
            self.files = iter(files)

        def _fetch(self):
            return next(self.files)

    cam = Files([jpg, commented, jpg, jpg])
    first = cam.grab()
    assert np.array_equal(cam.grab(), first)  # the same pixels in another file: not this check's to tell
    assert cam._stale.last == file_digest(commented)
    cam.grab()
    with pytest.raises(CameraError, match="same frame twice"):
        cam.grab()


def test_encoded_frames_are_decoded_and_checked_where_they_are_analysed(server):
    """A farm's Dask workers get the camera's bytes (grab_encoded): decoding them gives what grab() gives, with the
    same errors; a web page or bytes that are no image are refused at the camera (where it retries)."""
    from layerwatch.monitor.cameras import EncodedFrame, StaleCheck
    from layerwatch.monitor.parked import FrameNotParked, ParkCheck, ParkedCamera

    cam = SnapshotCamera(server + "/snap?action=snapshot", sleep=lambda s: None)
    assert cam.encoded and MjpegCamera(server + "/stream").encoded
    assert not SimCamera(lambda i: None).encoded and not FolderCamera(".").encoded  # these give arrays
    frame = cam.grab_encoded()
    assert isinstance(frame, EncodedFrame) and frame.stale_check and frame.where == cam.where
    stale = StaleCheck()
    img = frame.decode(stale)
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    with pytest.raises(CameraError, match="same frame twice"):
        frame.decode(stale)  # the frame again: a frozen stream, as grab() says
    assert np.array_equal(EncodedFrame(frame.data, "x", stale_check=False).decode(stale), img)  # no check asked
    stream = MjpegCamera(server + "/stream").grab_encoded()
    assert abs(int(stream.decode().mean()) - 128) <= 2
    sleeps = []
    with pytest.raises(CameraError, match="web page"):
        SnapshotCamera(server + "/html", retries=2, sleep=sleeps.append).grab_encoded()
    assert len(sleeps) == 2  # retried at the camera
    with pytest.raises(CameraError, match="not an image"):
        EncodedFrame(b"\xff\xd8 truncated", "x", False).decode()
    with pytest.raises(CameraError, match="1x1"):
        SnapshotCamera(server + "/tiny", sleep=lambda s: None).grab_encoded().decode()

    class Garbage(SnapshotCamera):
        def _fetch(self) -> bytes:
            return b"GIF89a not what a snapshot URL should send"

    with pytest.raises(CameraError, match="not an image"):
        Garbage(server + "/x", retries=0).grab_encoded()
    # a parked camera checks the head's position after the encoded frame too
    check = ParkCheck({0: (0.0, 0.0, 0.2)}, tolerance_mm=1.0)
    parked = ParkedCamera(cam, check, lambda: (0.0, 0.0, 0.2))
    assert parked.encoded and isinstance(parked.grab_encoded(), EncodedFrame)
    with pytest.raises(FrameNotParked):
        ParkedCamera(cam, check, lambda: (50.0, 0.0, 0.2)).grab_encoded()
