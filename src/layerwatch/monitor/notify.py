"""Alerts: Apprise URLs and a plain JSON webhook, rate-limited, never raising."""

from __future__ import annotations

import base64
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

from layerwatch.pipeline.policy import NotifySettings

__all__ = ["Notifier", "APPRISE_TYPES"]

log = logging.getLogger("layerwatch.monitor.notify")

#: our alert level -> Apprise ``notify_type`` (Apprise knows info/success/warning/failure)
APPRISE_TYPES = {"info": "info", "success": "success", "warning": "warning", "critical": "failure",
                 "error": "failure", "failure": "failure"}


class Notifier:
    """Send alerts to Apprise URLs and/or a JSON webhook.

    Parameters
    ----------
    settings : NotifySettings
        ``apprise_urls``, ``webhook_url`` and ``min_interval_s``.
    clock : callable
        Monotonic time source in s (tests pass their own).

    Notes
    -----
    The webhook receives ``{"title", "message", "level", "data",
    "image_base64", "image_name"}``. Apprise targets get the title, the
    message, the level as Apprise's notify type (``critical`` -> ``failure``)
    and the image as an attachment; an unreadable image is left out rather
    than losing the alert. The rate limit counts attempts, so a target that
    is down is not hammered. Failures are logged, never raised.
    """

    def __init__(self, settings: NotifySettings | None = None, clock=time.monotonic) -> None:
        self.settings = settings or NotifySettings()
        self._clock = clock
        self._last: float | None = None
        self.sent = 0
        self.suppressed = 0

    def notify(
        self,
        title: str,
        message: str,
        *,
        level: str = "warning",
        image: str | Path | bytes | np.ndarray | None = None,
        data: dict[str, Any] | None = None,
        force: bool = False,
    ) -> bool:
        """Send one alert unless rate-limited.

        Parameters
        ----------
        title, message : str
            Alert title and body.
        level : str
            ``"info"``, ``"warning"`` or ``"critical"``.
        image : path, bytes or ndarray, optional
            The overlay: a file, encoded image bytes (PNG/JPEG), or an
            (H, W) / (H, W, 3) uint8 BGR array (encoded as PNG).
        data : dict, optional
            Extra JSON values for the webhook.
        force : bool
            Ignore the rate limit (pauses are always sent).

        Returns
        -------
        bool
            True when at least one target accepted it.
        """
        now = self._clock()
        if not force and self._last is not None and now - self._last < self.settings.min_interval_s:
            self.suppressed += 1
            log.info("notification rate-limited: %s", title)
            return False
        self._last = now
        img_bytes, img_name = self._image(image)
        ok = False
        if self.settings.webhook_url:
            ok |= self._webhook(title, message, level, img_bytes, img_name, data)
        if self.settings.apprise_urls:
            ok |= self._apprise(title, message, level, img_bytes, img_name)
        if ok:
            self.sent += 1
        return ok

    @staticmethod
    def _image(image: str | Path | bytes | np.ndarray | None) -> tuple[bytes | None, str | None]:
        if image is None:
            return None, None
        if isinstance(image, np.ndarray):
            ok, buf = cv2.imencode(".png", image)
            if not ok:
                log.warning("notification image of shape %s could not be encoded", image.shape)
                return None, None
            return buf.tobytes(), "overlay.png"
        if isinstance(image, bytes):
            return image, "overlay.jpg" if image[:3] == b"\xff\xd8\xff" else "overlay.png"
        try:
            return Path(image).read_bytes(), Path(image).name
        except OSError as exc:
            log.warning("notification image %s unreadable: %s", image, exc)
            return None, None

    def _webhook(self, title, message, level, img, name, data) -> bool:
        body = {
            "title": title,
            "message": message,
            "level": level,
            "data": data or {},
            "image_base64": base64.b64encode(img).decode("ascii") if img else None,
            "image_name": name,
        }
        url = self.settings.webhook_url
        assert url is not None  # _send calls the webhook only when a URL is set
        try:
            r = httpx.post(url, json=body, timeout=10.0)
            r.raise_for_status()
            return True
        except Exception as exc:  # noqa: BLE001 - never raise into the monitor
            log.warning("webhook %s failed: %s", self.settings.webhook_url, exc)
            return False

    def _apprise(self, title, message, level, img, name) -> bool:
        try:
            import apprise  # optional extra (layerwatch[notify]): loaded only when apprise URLs are set
        except ImportError:
            log.warning("apprise is not installed; pip install layerwatch[notify]")
            return False
        try:
            ap = apprise.Apprise()
            for url in self.settings.apprise_urls:
                if not ap.add(url):
                    log.warning("apprise URL %s not understood; check it against the Apprise wiki", url.split("://")[0] + "://...")
            if len(ap) == 0:
                return False
            notify_type = APPRISE_TYPES.get(level, "warning")
            if img is None:
                return bool(ap.notify(title=title, body=message, notify_type=notify_type))
            # Apprise attaches files by path: hand it the bytes under their own name
            with tempfile.TemporaryDirectory(prefix="layerwatch-notify-") as tmp:
                path = Path(tmp) / (name or "overlay.png")
                path.write_bytes(img)
                return bool(ap.notify(title=title, body=message, notify_type=notify_type, attach=str(path)))
        except Exception as exc:  # noqa: BLE001 - never raise into the monitor
            log.warning("apprise notification failed: %s", exc)
            return False
