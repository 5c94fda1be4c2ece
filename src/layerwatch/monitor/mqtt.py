"""MQTT connections (Bambu Lab LAN mode, Home Assistant): one paho-mqtt client, its TLS and its checks.

paho-mqtt is an optional extra (``pip install 'layerwatch[mqtt]'``); it is imported only here,
when a connection is opened, so that the rest of layerwatch runs without it.
"""

from __future__ import annotations

import math
import re
import ssl
import uuid
from pathlib import Path
from typing import Any

from layerwatch.errors import ConfigError, require

__all__ = ["tls_context", "mqtt_client", "check_topic_part", "MAX_MESSAGE_BYTES"]

#: largest MQTT message the connectors parse, bytes (a Bambu ``pushall`` report is ~10 KB)
MAX_MESSAGE_BYTES = 1 << 20

_TOPIC_PART = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_topic_part(value: str, what: str) -> str:
    """``value`` if it is safe inside an MQTT topic (letters, digits, ``_``, ``-``; no ``/ + #``).

    Raises
    ------
    ConfigError
        Empty, longer than 64 characters, or with other characters.
    """
    if not isinstance(value, str) or not _TOPIC_PART.match(value):
        raise ConfigError(f"{what} {str(value)[:70]!r} must be 1-64 letters, digits, '_' or '-'; fix it in the URL.")
    return value


def tls_context(ca_file: str | Path | None, *, check_hostname: bool = False) -> ssl.SSLContext:
    """The client TLS context of an MQTT connection.

    Parameters
    ----------
    ca_file : str or Path, optional
        PEM file of the certificate authority that signed the broker's certificate; the chain is
        verified. ``None``: the connection is encrypted but the broker is not authenticated (what a
        Bambu printer's self-signed LAN certificate allows unless its CA is given).
    check_hostname : bool
        Also match the certificate's name with the host (Bambu printers name their serial, not
        their address: off for them).

    Raises
    ------
    ConfigError
        The CA file cannot be read or holds no certificate.
    """
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    if ca_file is None:
        ctx.check_hostname = False
        ctx.verify_mode = ssl.CERT_NONE
        return ctx
    try:
        ctx.load_verify_locations(cafile=str(Path(ca_file).expanduser()))
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(f"{ca_file}: cannot load the CA certificate ({exc}); give a PEM file with ?ca=FILE.") from None
    ctx.check_hostname = check_hostname
    ctx.verify_mode = ssl.CERT_REQUIRED
    return ctx


def mqtt_client(*, user: str | None, password: str | None, tls: ssl.SSLContext | None, prefix: str,
                reconnect_s: tuple[float, float] = (0.5, 5.0)) -> Any:
    """A paho-mqtt client (MQTT 3.1.1, callback API 2) with credentials, TLS and reconnect back-off set.

    Parameters
    ----------
    user, password : str or None
    tls : ssl.SSLContext or None
        ``None``: plain TCP.
    prefix : str
        Client id prefix (a random suffix keeps two layerwatch processes apart).
    reconnect_s : (float, float)
        First and largest wait between reconnect attempts, s.

    Raises
    ------
    MissingExtraError
        paho-mqtt is not installed.
    """
    lo, hi = reconnect_s
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi <= 600):
        raise ConfigError("MQTT reconnect waits must be finite, 0 < first <= largest <= 600 s.")
    # optional extra: only users of Bambu LAN mode or Home Assistant need paho-mqtt
    client_mod = require("paho.mqtt.client", "mqtt", "MQTT (Bambu Lab LAN mode, Home Assistant)")
    client = client_mod.Client(client_mod.CallbackAPIVersion.VERSION2,
                               client_id=f"{prefix}-{uuid.uuid4().hex[:8]}", protocol=client_mod.MQTTv311)
    if user is not None:
        client.username_pw_set(user, password)
    if tls is not None:
        client.tls_set_context(tls)
    client.reconnect_delay_set(min_delay=lo, max_delay=hi)
    return client
