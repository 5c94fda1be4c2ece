"""CLI verbs for the history and the dashboard: ``history``, ``report``, ``serve``."""

from __future__ import annotations

import logging
import os
import ssl
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from layerwatch.cli import console
from layerwatch.cli.params import WRITE_DB, WRITE_DIR, Finite
from layerwatch.errors import ConfigError, require
from layerwatch.farm import Farm, load_farm
from layerwatch.storage.history import History
from layerwatch.web.report import build_report
from layerwatch.web.token import is_loopback, load_or_create_token
from layerwatch.web.virtual import virtual_printer

__all__ = ["register", "default_db"]


def default_db() -> Path:
    """``$LAYERWATCH_DB`` or ``~/.local/share/layerwatch/history.db``."""
    env = os.environ.get("LAYERWATCH_DB")
    return Path(env) if env else Path.home() / ".local" / "share" / "layerwatch" / "history.db"


DbOpt = Annotated[Path | None, typer.Option("--db", parser=WRITE_DB, help="History database (default $LAYERWATCH_DB or ~/.local/share/layerwatch/history.db).")]


def _open(db: Path | None):
    return History(db or default_db())


#: what writes a history database, for the read-only verbs' messages
_WRITERS = "`layerwatch serve` and `layerwatch monitor --history FILE` write one"


def _existing_db(db: Path | None) -> Path | None:
    """The database the read-only verbs (``history``, ``report``) read; None when the default one is not made yet.

    They create nothing: a ``--db`` that names no database file is a mistake (one line, exit 2), where
    opening it would leave a new empty database, and its folders, at the mistyped path.

    Raises
    ------
    ConfigError
        ``--db`` names no file, or something that is not a file.
    """
    path = db or default_db()
    if path.is_file():
        return path
    if db is None and not path.exists():
        return None
    what = "is not a file" if path.exists() else "does not exist"
    raise ConfigError(f"history database {path} {what}; give the --db of the print's history ({_WRITERS}).")


def history(db: DbOpt = None) -> None:
    """List the jobs in the history database (a missing database is listed as empty, not created)."""
    path = _existing_db(db)
    if path is None:
        console.print(f"0 job(s): no history database at {default_db()} yet ({_WRITERS}).", soft_wrap=True)
        return
    with _open(path) as h:
        jobs = h.jobs()
    table = Table(title=f"{len(jobs)} job(s)")
    for col in ("job", "printer", "part", "started", "layers", "max a%", "outcome"):
        table.add_column(col, justify="right" if col in ("job", "layers", "max a%") else "left")
    for j in jobs:
        mx = j["max_anomaly_ratio"]
        table.add_row(str(j["id"]), j["printer"], j["part"] or "", time.strftime("%Y-%m-%d %H:%M", time.localtime(j["started"])),
                      str(j["n_layers"]), "–" if mx is None else f"{100 * mx:.1f} %", j["outcome"] or "[green]running[/]")
    console.print(table)


def report(
    job: Annotated[int, typer.Argument(parser=Finite(1, 2**63 - 1, integer=True), help="Job id (see `layerwatch history`).")],
    db: DbOpt = None,
    out: Annotated[Path, typer.Option("--out", "-o", parser=WRITE_DIR, help="Output folder for report.html.")] = Path("report"),
    images: Annotated[Path | None, typer.Option("--images", exists=True, file_okay=False, help="Folder the stored image paths are relative to (default: beside the database).")] = None,
) -> None:
    """Write a self-contained HTML report of one job."""
    dbp = _existing_db(db)
    if dbp is None:
        raise ConfigError(f"no history database at {default_db()}; give the --db of the print's history ({_WRITERS}).")
    with _open(dbp) as h:
        path = build_report(h, job, out, image_root=images)
    console.print(f"report written to [bold]{path}[/]")


def _check_tls(certfile: Path | None, keyfile: Path | None) -> None:
    """Refuse a certificate/key pair that will not load, before the server starts (one line, exit 2)."""
    if certfile is None and keyfile is None:
        return
    if certfile is None:
        raise ConfigError("--ssl-keyfile needs --ssl-certfile (the certificate it belongs to).")
    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(
            str(certfile), str(keyfile) if keyfile is not None else None)
    except (ssl.SSLError, OSError, ValueError) as exc:
        raise ConfigError(f"--ssl-certfile {certfile} / --ssl-keyfile {keyfile} do not load as a PEM certificate "
                          f"and its private key ({exc}); give the files your TLS tool wrote.") from None


def serve(
    db: DbOpt = None,
    host: Annotated[str, typer.Option("--host", help="Interface to bind; anything but loopback requires the token.")] = "127.0.0.1",
    port: Annotated[int, typer.Option("--port", parser=Finite(1, 65535, integer=True), help="TCP port to listen on.")] = 8765,
    images: Annotated[Path | None, typer.Option("--images", exists=True, file_okay=False, help="Artifacts folder: the layers' recorded pictures under it are served, nothing else (default: beside the database).")] = None,
    virtual: Annotated[bool, typer.Option("--virtual", help="Attach a virtual printer (for trying the buttons).")] = False,
    allowed_host: Annotated[list[str] | None, typer.Option("--allowed-host", help="Host name the dashboard answers to besides loopback names (repeatable), e.g. printer.local.")] = None,
    ssl_certfile: Annotated[Path | None, typer.Option("--ssl-certfile", exists=True, dir_okay=False, help="Serve HTTPS with this certificate (PEM); session cookies become Secure.")] = None,
    ssl_keyfile: Annotated[Path | None, typer.Option("--ssl-keyfile", exists=True, dir_okay=False, help="Private key of --ssl-certfile (PEM).")] = None,
    farm: Annotated[Path | None, typer.Option("--farm", exists=True, dir_okay=False, help="farm.toml: watch every [[printers]] table of it (see docs/farm.md).")] = None,
    scheduler: Annotated[str | None, typer.Option("--scheduler", help="With --farm: run the per-layer work on this Dask scheduler (tcp://host:8786, or 'local'); default: local threads.")] = None,
    workers: Annotated[int | None, typer.Option("--workers", parser=Finite(1, 256, integer=True), help="With --farm: shared analysis workers (default: the farm file's, else 2).")] = None,
) -> None:
    """Serve the dashboard (FastAPI + uvicorn); see docs/security.md for running it on a network."""
    uvicorn = require("uvicorn", "web", "The dashboard server")
    require("fastapi", "web", "The dashboard")
    from layerwatch.web.app import (
        create_app,  # optional extra: FastAPI (`web`); history/report work without it
    )

    _check_tls(ssl_certfile, ssl_keyfile)
    dbp = db or default_db()
    h = _open(dbp)
    token = None
    token_file = dbp.with_suffix(".token")
    scheme = "https" if ssl_certfile else "http"
    if not is_loopback(host):
        token, created = load_or_create_token(token_file)
        if created:
            console.print(f"[bold yellow]access token (shown once, stored in {token_file}):[/] {token}")
        console.print(f"log in at {scheme}://{host}:{port}/login with the token")
    if farm is None and (scheduler is not None or workers is not None):
        raise ConfigError("--scheduler and --workers apply to a farm; add --farm farm.toml.")
    fleet = _farm(farm, h, scheduler, workers) if farm is not None else None
    printers = dict(fleet.printers) if fleet is not None else {}
    if virtual:
        printers["virtual"] = virtual_printer()
    app = create_app(h, printers=printers, token=token, image_root=images or dbp.parent,
                     allowed_hosts=allowed_host or None, token_file=token_file)
    console.print(f"dashboard on {scheme}://{host}:{port}/" + (f" (farm: {len(printers)} printers)" if fleet else ""))
    try:
        if fleet is not None:
            fleet.start()
        uvicorn.run(app, host=host, port=port, log_level="warning",
                    ssl_certfile=str(ssl_certfile) if ssl_certfile else None,
                    ssl_keyfile=str(ssl_keyfile) if ssl_keyfile else None)
    finally:
        if fleet is not None:
            fleet.stop()


def _farm(path: Path, history, scheduler: str | None, workers: int | None):
    """The farm of ``path`` (validated: one line naming the printer and key, exit 2), not started yet."""
    cfg = load_farm(path)
    if scheduler is not None and not (scheduler == "local" or scheduler.startswith(("tcp://", "tls://"))):
        raise ConfigError(f"--scheduler {scheduler!r} is not a Dask scheduler address; use tcp://host:8786 or local.")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s %(message)s")
    return Farm(cfg, history, scheduler=scheduler, workers=workers)


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.command("history")(history)
    app.command("report")(report)
    app.command("serve")(serve)
