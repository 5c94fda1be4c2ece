"""Printer host API keys: where they come from, and keeping them out of logs and process lists.

A key given on the command line (``octoprint://host?key=...``) is visible to
every local user in the process list, so keys are read, highest precedence
first, from a key file (``--key-file``), an environment variable
(:data:`ENV_VARS`) or the job file's ``[host] api_key``; a key in the URL is
still accepted, with a warning. :func:`redact_url` is applied to every URL
that reaches a log line, an error message or the history database.
"""

from __future__ import annotations

import logging
import os
import re
import stat
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

from layerwatch.errors import ConfigError
from layerwatch.pipeline.watch_settings import HostSettings

__all__ = ["ENV_VARS", "HostSettings", "read_key_file", "split_url_key", "redact_url", "resolve_key"]

log = logging.getLogger("layerwatch.monitor.keys")

#: Environment variable holding the API key, per host software.
#: PrusaLink: the password shown on the printer; Bambu Lab: the LAN-mode access code; mqtt: the
#: password of the Home Assistant broker's user.
ENV_VARS = {"octoprint": "LAYERWATCH_OCTOPRINT_KEY", "moonraker": "LAYERWATCH_MOONRAKER_KEY",
            "prusalink": "LAYERWATCH_PRUSALINK_KEY", "bambu": "LAYERWATCH_BAMBU_KEY", "mqtt": "LAYERWATCH_MQTT_KEY"}

#: Query parameters whose values are secrets.
_SECRET_PARAMS = frozenset({"key", "apikey", "api_key", "token", "access_token", "password", "secret"})
_MAX_KEY_FILE_BYTES = 4096
_KEY = re.compile(r"^[\x21-\x7e]{1,512}$")  # printable ASCII without spaces


def _check_key(key: str, where: str) -> str:
    key = key.strip()
    if not _KEY.match(key):
        raise ConfigError(f"{where}: the API key must be 1-512 printable characters without spaces; "
                          "copy it again from the printer host's settings.")
    return key


def read_key_file(path: str | Path) -> str:
    """The API key in the first non-empty line of ``path``.

    A file that other users can read is refused (its key is no secret any more);
    one the group can read is used with a warning.

    Raises
    ------
    ConfigError
        Missing/unreadable file, world-readable file, or no key in it.
    """
    p = Path(path).expanduser()
    try:
        mode = p.stat().st_mode
        if stat.S_ISREG(mode) and mode & stat.S_IROTH:
            raise ConfigError(f"{p}: the key file is readable by every user; run `chmod 600 {p}` "
                              "(and consider a new API key).")
        if mode & stat.S_IRGRP:
            log.warning("%s: the key file is readable by its group; `chmod 600 %s` keeps the key private", p, p)
        with p.open("rb") as fh:
            data = fh.read(_MAX_KEY_FILE_BYTES)
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the key file ({exc.strerror}); check --key-file.") from None
    lines = [ln.strip() for ln in data.decode("utf-8", "replace").splitlines() if ln.strip()]
    if not lines:
        raise ConfigError(f"{p}: the key file is empty; put the API key on its first line.")
    return _check_key(lines[0], str(p))


def split_url_key(url: str) -> tuple[str, str | None]:
    """``url`` without its ``key=`` query parameter, and that key (or None)."""
    parts = urlsplit(url)
    query = parse_qsl(parts.query, keep_blank_values=True)
    key = next((v for k, v in query if k == "key"), None)
    rest = urlencode([(k, v) for k, v in query if k != "key"])
    return urlunsplit(parts._replace(query=rest)), key or None


def redact_url(url: str) -> str:
    """``url`` with secret query values and a userinfo password replaced by ``***``."""
    try:
        parts = urlsplit(url)
        query = [(k, "***" if k.lower() in _SECRET_PARAMS else v)
                 for k, v in parse_qsl(parts.query, keep_blank_values=True)]
        netloc = parts.netloc
        if "@" in netloc:
            user, host = netloc.rsplit("@", 1)
            netloc = f"{user.split(':', 1)[0]}:***@{host}" if ":" in user else netloc
        return urlunsplit(parts._replace(netloc=netloc, query=urlencode(query, safe="*")))
    except ValueError:  # not a URL at all: keep nothing after a '?'
        return url.split("?", 1)[0]


def resolve_key(host: str, url: str, *, key_file: str | Path | None = None, config_key: str | None = None,
                env: Mapping[str, str] | None = None) -> tuple[str | None, str]:
    """The API key for ``host`` and where it came from.

    Precedence: ``key_file`` (``--key-file`` or ``[host] key_file``) > environment variable
    (:data:`ENV_VARS`) > job file ``[host] api_key`` > ``?key=`` in the URL (with a warning).

    Parameters
    ----------
    host : str
        ``"octoprint"`` or ``"moonraker"``.
    url : str
        The printer URL as given.
    key_file : str or Path, optional
    config_key : str, optional
        The job file's key.
    env : mapping, optional
        Environment (default ``os.environ``).

    Returns
    -------
    key : str or None
    source : str
        ``"key file"``, ``"LAYERWATCH_OCTOPRINT_KEY"``, ``"job file"``, ``"URL"`` or ``"none"``.
    """
    env = os.environ if env is None else env
    var = ENV_VARS.get(host, "")
    if key_file is not None:
        return read_key_file(key_file), "key file"
    if var and env.get(var, "").strip():
        return _check_key(env[var], var), var
    if config_key:
        return _check_key(config_key, "[host] api_key"), "job file"
    _, key = split_url_key(url)
    if key:
        log.warning("the API key is in the printer URL, where every local user can read it in the process list; "
                    "use %s, --key-file or [host] api_key in the job file instead", var or "--key-file")
        return key, "URL"
    return None, "none"
