"""Alerts: Apprise URLs and a plain JSON webhook, rate-limited, never raising."""

from __future__ import annotations

import base64
import logging
import time
from pathlib import Path
from typing import Any

from layerwatch.monitor.settings import NotifySettings

__all__ = ["Notifier"]

log = logging.getLogger("layerwatch.monitor.notify")


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
    "image_base64", "image_name"}``. Failures are logged, never raised.
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
        image: str | Path | bytes | None = None,
        data: dict[str, Any] | None = None,
        force: bool = False,
    ) -> bool:
        """Send one alert unless rate-limited; returns True when sent to at least one target."""
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
            ok |= self._apprise(title, message, image if isinstance(image, (str, Path)) else None)
        if ok:
            self.sent += 1
        return ok

    @staticmethod
    def _image(image: str | Path | bytes | None) -> tuple[bytes | None, str | None]:
        if image is None:
            return None, None
        if isinstance(image, bytes):
            return image, "overlay.png"
        try:
            return Path(image).read_bytes(), Path(image).name
        except OSError as exc:
            log.warning("notification image %s unreadable: %s", image, exc)
            return None, None

    def _webhook(self, title, message, level, img, name, data) -> bool:
        import httpx

        body = {
            "title": title,
            "message": message,
            "level": level,
            "data": data or {},
            "image_base64": base64.b64encode(img).decode("ascii") if img else None,
            "image_name": name,
        }
        try:
            r = httpx.post(self.settings.webhook_url, json=body, timeout=10.0)
            r.raise_for_status()
            return True
        except Exception as exc:  # noqa: BLE001 - never raise into the monitor
            log.warning("webhook %s failed: %s", self.settings.webhook_url, exc)
            return False

    def _apprise(self, title, message, attach) -> bool:
        try:
            import apprise
        except ImportError:
            log.warning("apprise is not installed; pip install layerwatch[notify]")
            return False
        try:
            ap = apprise.Apprise()
            for url in self.settings.apprise_urls:
                ap.add(url)
            return bool(ap.notify(title=title, body=message, attach=str(attach) if attach else None))
        except Exception as exc:  # noqa: BLE001
            log.warning("apprise notification failed: %s", exc)
            return False
