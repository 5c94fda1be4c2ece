"""Settings of watching a printer that a job config carries: the host's credentials and fault alerts.

They are read by :mod:`layerwatch.monitor` (``monitor/printers/keys.py``, ``monitor/health.py``) but
belong to the job config (:class:`~layerwatch.pipeline.config.JobConfig`), which sits below the
monitor in the import layers, so they are defined here.
"""

from __future__ import annotations

from pydantic import Field, SecretStr

from layerwatch.settings_base import Section

__all__ = ["FaultSettings", "HostSettings"]


class FaultSettings(Section):
    """When printer-host and camera faults are notified (config section ``[faults]``).

    Attributes
    ----------
    printer_grace_s : float
        Notify when the printer host has been unreachable (or answered nonsense) this long, s;
        shorter outages (a host restart) are logged and shown on the dashboard only.
    camera_alert_after : int
        Notify after this many unusable frames in a row (camera errors or frames the
        camera-fault gate refused).
    warn_interval_s : float
        Least time between two log warnings about the same ongoing fault, s.
    """

    printer_grace_s: float = Field(30.0, ge=0, le=86_400)
    camera_alert_after: int = Field(3, ge=1, le=10_000)
    warn_interval_s: float = Field(60.0, ge=0, le=86_400)


class HostSettings(Section):
    """Printer host credentials (config section ``[host]``; never taken from the dashboard).

    Attributes
    ----------
    api_key : SecretStr or None
        The host's API key (OctoPrint: Settings > API; Moonraker: ``[authorization]``).
        Stored and shown as ``**********``.
    key_file : str or None
        File whose first line is the API key (kept ``chmod 600``).
    """

    api_key: SecretStr | None = None
    key_file: str | None = Field(None, min_length=1)
