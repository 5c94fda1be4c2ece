"""Camera sources: snapshot URL, MJPEG stream, V4L2/USB, watched folder, simulator.

Every source has ``grab() -> ndarray`` (BGR uint8, shape (H, W, 3)) and
raises :class:`~layerwatch.errors.CameraError` with a one-line fix on
failure: timeouts (after retries), HTML instead of an image, tiny (1x1)
images, or the same frame twice in a row (a frozen stream).
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

from layerwatch.errors import CameraError
from layerwatch.monitor.jpeg_decode import decode_jpeg

__all__ = ["Camera", "SnapshotCamera", "MjpegCamera", "DeviceCamera", "FolderCamera", "SimCamera", "open_camera", "decode_image",
           "frame_digest", "file_digest", "EncodedFrame", "StaleCheck", "sniff_image"]

MIN_SIDE = 16


def _web_page(data: bytes, where: str) -> None:
    head = data[:64].lstrip().lower()
    if head.startswith((b"<!doctype", b"<html", b"<?xml", b"{")):
        raise CameraError(f"{where} returned a web page, not an image; use the snapshot URL (e.g. ...?action=snapshot).")


def _not_an_image(data: bytes, where: str) -> CameraError:
    return CameraError(f"{where} returned {len(data)} bytes that are not an image; check the camera URL.")


#: how JPEG and PNG files start
_MAGIC = (b"\xff\xd8", b"\x89PNG\r\n\x1a\n")


def sniff_image(data: bytes, where: str) -> bytes:
    """``data`` when it looks like a JPEG or PNG file (by its first bytes, without decoding), else CameraError.

    The cheap part of :func:`decode_image`, for frames decoded elsewhere (:class:`EncodedFrame`):
    a web page or bytes that are no image file are refused where the camera can still retry.
    """
    _web_page(data, where)
    if not data.startswith(_MAGIC):
        raise _not_an_image(data, where)
    return data


def decode_image(data: bytes, where: str) -> np.ndarray:
    """Decode JPEG/PNG bytes to a BGR uint8 (H, W, 3) image or raise CameraError.

    A JPEG goes to libjpeg-turbo directly where :func:`~layerwatch.monitor.jpeg_decode.decode_jpeg` can
    take it (the optional ``simplejpeg``: the same pixels, ~10 % less CPU), everything else to OpenCV.
    """
    _web_page(data, where)
    img = decode_jpeg(data) if data else None
    if img is None and data:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise _not_an_image(data, where)
    return check_frame(img, where)


def check_frame(img: np.ndarray, where: str) -> np.ndarray:
    """Reject placeholder frames (smaller than 16 px a side)."""
    if img.ndim < 2 or min(img.shape[:2]) < MIN_SIDE:
        raise CameraError(f"{where} gave a {img.shape[1]}x{img.shape[0]} image (a placeholder?); check that the camera is streaming.")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])


def frame_digest(img: np.ndarray) -> tuple[int, int]:
    """A 64-bit fingerprint of a frame's pixels (CRC-32 and Adler-32 of its bytes, read in place).

    For the stale-frame check (the same frame twice), not against an adversary: two checksums in one
    pass each over a 1080p frame cost ~3.5 ms, half a cryptographic hash with the copy it needed.
    """
    buf = np.ascontiguousarray(img).data.cast("B")
    return zlib.crc32(buf), zlib.adler32(buf)


def file_digest(data: bytes) -> tuple[int, int]:
    """:func:`frame_digest` of a camera's encoded file (JPEG/PNG bytes) instead of its decoded pixels.

    The same file decodes to the same pixels (the decoder is deterministic), and a 1080p JPEG is
    ~0.3-0.5 MB against 6 MB decoded: ~0.25 ms instead of ~3.3.
    """
    return zlib.crc32(data), zlib.adler32(data)


class StaleCheck:
    """The stale-frame check: a frame identical to the previous one is a frozen stream.

    Holds the last frame's fingerprint (a camera's, or a farm job's on the worker that decodes its
    frames): :func:`file_digest` of the file for a camera that sends JPEG/PNG files (byte-identical
    files), else :func:`frame_digest` of the pixels. A camera that re-encodes the same pixels into
    other bytes (a timestamp in the file's metadata) passes this check; the camera-fault gate's
    repeated-frame check (``frame_quality``: no change from the previous usable frame) tells it.
    """

    def __init__(self) -> None:
        self.last: tuple[int, int] | None = None

    def __call__(self, img: np.ndarray, where: str) -> np.ndarray:
        """``img``, remembered; raises CameraError when it repeats the previous frame."""
        self._seen(frame_digest(img), where)
        return img

    def file(self, data: bytes, where: str) -> None:
        """The camera's encoded file ``data``, remembered; raises CameraError when it repeats the previous one."""
        self._seen(file_digest(data), where)

    def _seen(self, digest: tuple[int, int], where: str) -> None:
        if digest == self.last:
            raise CameraError(f"{where} returned the same frame twice; the stream looks frozen, restart the camera service.")
        self.last = digest


class EncodedFrame:
    """A camera frame as the camera sent it (JPEG or PNG bytes), to be decoded where it is analysed.

    A farm on a Dask cluster sends these to its workers (a 1080p JPEG is ~0.3 MB, decoded 6 MB);
    :meth:`decode` does there what :meth:`Camera.grab` does after reading the bytes.

    Parameters
    ----------
    data : bytes
        The file's bytes (checked with :func:`sniff_image`).
    where : str
        The camera, for messages.
    stale_check : bool
        The camera checks for repeated frames (the decoder's :class:`StaleCheck` then runs).
    """

    __slots__ = ("data", "where", "stale_check")

    def __init__(self, data: bytes, where: str, stale_check: bool) -> None:
        self.data, self.where, self.stale_check = data, where, bool(stale_check)

    def decode(self, stale: StaleCheck | None = None) -> np.ndarray:
        """The frame, BGR uint8 (H, W, 3); CameraError as :meth:`Camera.grab` raises it (not an image, a
        repeated frame when ``stale`` is given and the camera checks)."""
        img = decode_image(self.data, self.where)
        if stale is not None and self.stale_check:
            stale.file(self.data, self.where)  # after decoding: bytes that are no image are that error, as in grab()
        return img


class Camera:
    """Base: retries, settle delay and the stale-frame check around ``_read()``.

    Parameters
    ----------
    retries : int
        Extra attempts after a failure.
    settle_s : float
        Wait before grabbing (vibration after the nozzle parks), s.
    stale_check : bool
        Raise when a frame is byte-identical to the previous one.
    """

    where = "camera"

    def __init__(self, *, retries: int = 2, settle_s: float = 0.0, stale_check: bool = True,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.retries = int(retries)
        self.settle_s = float(settle_s)
        self.stale_check = stale_check
        self._sleep = sleep
        self._stale = StaleCheck()

    def _read(self) -> np.ndarray:
        return decode_image(self._fetch(), self.where)

    def _fetch(self) -> bytes:
        """The frame's encoded bytes (sources whose frames arrive as JPEG/PNG files override it)."""
        raise NotImplementedError

    @property
    def encoded(self) -> bool:
        """The frames arrive encoded: :meth:`grab_encoded` gives them without decoding."""
        return type(self)._fetch is not Camera._fetch

    def _attempts(self, read: Callable[[], Any]) -> Any:
        """``read()`` after the settle delay, retried on CameraError."""
        if self.settle_s > 0:
            self._sleep(self.settle_s)
        err: CameraError | None = None
        for attempt in range(self.retries + 1):
            try:
                return read()
            except CameraError as exc:
                err = exc
                if attempt < self.retries:
                    self._sleep(min(0.2 * 2**attempt, 2.0))
        assert err is not None
        raise err

    def grab(self) -> np.ndarray:
        """One fresh frame, BGR uint8 (H, W, 3).

        A camera whose frames arrive as files (:attr:`encoded`, read by the base class) has the file's bytes
        fingerprinted for the stale-frame check, not the decoded pixels (:class:`StaleCheck`).
        """
        if self.stale_check and self.encoded and type(self)._read is Camera._read:
            data, img = self._attempts(self._fetch_decoded)
            self._stale.file(data, self.where)
            return img
        img = self._attempts(self._read)
        return self._stale(img, self.where) if self.stale_check else img

    def _fetch_decoded(self) -> tuple[bytes, np.ndarray]:
        """The frame's file and its pixels (:meth:`_read` keeping the bytes)."""
        data = self._fetch()
        return data, decode_image(data, self.where)

    def grab_encoded(self) -> EncodedFrame:
        """One fresh frame as the camera sent it (only when :attr:`encoded`): retried as :meth:`grab` is when the
        bytes are no image file (:func:`sniff_image`); decoding and the stale-frame check are the caller's
        (:meth:`EncodedFrame.decode`)."""
        return EncodedFrame(self._attempts(lambda: sniff_image(self._fetch(), self.where)), self.where,
                            self.stale_check)

    def close(self) -> None:
        return None


class SnapshotCamera(Camera):
    """HTTP snapshot URL (mjpg-streamer/ustreamer/crowsnest ``?action=snapshot``)."""

    def __init__(self, url: str, *, timeout_s: float = 5.0, **kw) -> None:
        super().__init__(**kw)
        self.url, self.timeout_s, self.where = url, timeout_s, f"camera {url}"

    def _fetch(self) -> bytes:
        try:
            r = httpx.get(self.url, timeout=self.timeout_s, follow_redirects=True)
        except httpx.HTTPError as exc:
            raise CameraError(f"{self.where} unreachable ({type(exc).__name__}); check the URL and that the camera service runs.") from exc
        if r.status_code != 200:
            raise CameraError(f"{self.where} answered HTTP {r.status_code}; check the snapshot URL.")
        return r.content


class MjpegCamera(Camera):
    """MJPEG stream (``multipart/x-mixed-replace``): reads the first complete JPEG part."""

    def __init__(self, url: str, *, timeout_s: float = 5.0, max_bytes: int = 20_000_000, **kw) -> None:
        super().__init__(**kw)
        self.url, self.timeout_s, self.max_bytes, self.where = url, timeout_s, max_bytes, f"stream {url}"

    def _fetch(self) -> bytes:
        buf = b""
        try:
            with httpx.stream("GET", self.url, timeout=self.timeout_s) as r:
                if r.status_code != 200:
                    raise CameraError(f"{self.where} answered HTTP {r.status_code}; check the stream URL.")
                ctype = r.headers.get("content-type", "")
                if "multipart" not in ctype:
                    return r.read()
                for chunk in r.iter_bytes():
                    buf += chunk
                    frame = _first_jpeg(buf)
                    if frame is not None:
                        return frame
                    if len(buf) > self.max_bytes:
                        break
        except httpx.HTTPError as exc:
            raise CameraError(f"{self.where} unreachable ({type(exc).__name__}); check the URL and that the camera service runs.") from exc
        raise CameraError(f"{self.where} sent no complete JPEG frame; check that it is an MJPEG stream.")


def _first_jpeg(buf: bytes) -> bytes | None:
    """First complete JPEG (SOI..EOI) in a multipart buffer, or None."""
    start = buf.find(b"\xff\xd8")
    if start < 0:
        return None
    end = buf.find(b"\xff\xd9", start + 2)
    return None if end < 0 else buf[start : end + 2]


class DeviceCamera(Camera):
    """Local V4L2/USB camera through ``cv2.VideoCapture``."""

    def __init__(self, device: int | str = 0, *, flush: int = 3, **kw) -> None:
        super().__init__(**kw)
        self.device, self.flush, self.where = device, flush, f"camera device {device}"
        self._cap: cv2.VideoCapture | None = None

    def _read(self) -> np.ndarray:
        if self._cap is None or not self._cap.isOpened():
            self._cap = cv2.VideoCapture(self.device)
            if not self._cap.isOpened():
                self._cap = None
                raise CameraError(f"{self.where} cannot be opened; check the device path and permissions (video group).")
        for _ in range(self.flush):  # drop buffered, older frames
            self._cap.grab()
        ok, img = self._cap.read()
        if not ok or img is None:
            raise CameraError(f"{self.where} returned no frame; check the cable and that no other program uses it.")
        return check_frame(img, self.where)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class FolderCamera(Camera):
    """Watched folder: each grab returns the newest image file not returned yet."""

    EXT = (".jpg", ".jpeg", ".png", ".bmp")

    def __init__(self, folder: str | Path, **kw) -> None:
        kw.setdefault("retries", 0)
        super().__init__(**kw)
        self.folder, self.where = Path(folder), f"folder {folder}"
        self._seen: set[Path] = set()

    def _read(self) -> np.ndarray:
        if not self.folder.is_dir():
            raise CameraError(f"{self.where} does not exist; create it or fix the path.")
        files = sorted((p for p in self.folder.iterdir() if p.suffix.lower() in self.EXT and p not in self._seen),
                       key=lambda p: (p.stat().st_mtime, p.name))
        if not files:
            raise CameraError(f"{self.where} has no new image; check that the capture script writes there.")
        path = files[0]
        self._seen.add(path)
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise CameraError(f"{path} is not a readable image; remove it.")
        return check_frame(img, str(path))


class SimCamera(Camera):
    """Simulator source: ``frame(layer) -> ndarray``; call :meth:`set_layer` before grabbing."""

    def __init__(self, frame: Callable[[int], np.ndarray], **kw) -> None:
        kw.setdefault("stale_check", False)
        super().__init__(**kw)
        self.frame, self.layer, self.where = frame, 0, "simulated camera"

    def set_layer(self, layer: int) -> None:
        self.layer = int(layer)

    def _read(self) -> np.ndarray:
        return check_frame(np.asarray(self.frame(self.layer)), self.where)


def open_camera(spec: str, **kw) -> Camera:
    """Camera from a CLI spec: ``http(s)://...`` (``stream`` in the URL -> MJPEG), ``file:DIR``, ``/dev/videoN`` or ``v4l2:N``."""
    if spec.startswith(("http://", "https://")):
        return MjpegCamera(spec, **kw) if "action=stream" in spec or spec.rstrip("/").endswith("stream") else SnapshotCamera(spec, **kw)
    if spec.startswith("file:"):
        return FolderCamera(spec[5:], **kw)
    if spec.startswith("/dev/video") or spec.startswith("v4l2:"):
        dev = spec[5:] if spec.startswith("v4l2:") else spec
        return DeviceCamera(int(dev) if dev.isdigit() else dev, **kw)
    raise CameraError(f"unknown camera {spec!r}; use http://..., file:DIR, /dev/videoN or sim.")
