"""``layerwatch monitor``: watch a print on OctoPrint, Moonraker or the virtual printer."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

__all__ = ["register", "monitor_config", "dashboard_settings"]

SOURCES = ("file", "dashboard", "recommended")  # highest precedence first; "default" = the section's built-in values


def dashboard_settings(history) -> dict[str, dict]:
    """The settings the dashboard saved in ``history`` that differ from what it shows unsaved.

    The dashboard stores the whole job config it showed (``PUT``/``PATCH /api/settings``); unsaved, it shows
    the recommended settings (:func:`~layerwatch.evaluate.recommended.recommended_config`), so a key it never
    changed holds the recommended value; only the changed keys form the "dashboard" layer. (A key
    deliberately set back to its recommended value is indistinguishable from an untouched one, and the
    result is the same.)

    Parameters
    ----------
    history : History
        Open history database (schema >= 2, table ``settings``).

    Returns
    -------
    dict of str to dict
        Per section, the keys to apply (JSON values), e.g. ``{"policy": {"pause_ratio": 0.05}}``.

    Raises
    ------
    ConfigError
        The saved settings no longer validate (e.g. saved by another layerwatch version).
    """
    from pydantic import ValidationError

    from layerwatch.config import JobConfig
    from layerwatch.errors import ConfigError
    from layerwatch.web.app import SETTINGS_KEY

    saved = history.setting(SETTINGS_KEY)
    if saved is None:
        return {}
    try:
        cfg = JobConfig.model_validate(saved)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "settings"
        msg = " ".join(str(err["msg"]).split())
        raise ConfigError(f"{history.path}: the dashboard's saved setting {where} is invalid ({msg}); save the "
                          "settings again in the dashboard (layerwatch serve --db ...) or drop --history.") from None
    from layerwatch.evaluate.recommended import recommended_config

    base = recommended_config().model_dump(mode="json")
    out: dict[str, dict] = {}
    for section, values in cfg.model_dump(mode="json").items():
        changed = {k: v for k, v in values.items() if v != base[section].get(k)}
        if changed:
            out[section] = changed
    return out


def monitor_config(path: Path | None, history=None):
    """The monitor's job config and where each section's values came from.

    Precedence, per key: the job file's own keys > the dashboard's saved settings (:func:`dashboard_settings`)
    > the evaluation's recommended settings (:data:`layerwatch.evaluate.recommended.RECOMMENDED`) > the
    sections' built-in defaults.

    Parameters
    ----------
    path : Path or None
        Job config TOML (``--config``, or the bundled example's job file).
    history : History or None
        Database whose dashboard settings apply (``--history``).

    Returns
    -------
    cfg : JobConfig
    sources : dict of str to str
        Per section, the sources whose keys are in force, highest first, joined by ``+``
        (``"file+recommended"``), or ``"default"``.

    Raises
    ------
    ConfigError
        Unreadable or invalid file or saved settings (one line naming the fix).
    """
    import tomllib

    from layerwatch.config import JobConfig, load_config
    from layerwatch.evaluate.recommended import RECOMMENDED

    dash = dashboard_settings(history) if history is not None else {}
    dash.pop("host", None)  # printer credentials come from the job file, the environment or a key file only
    defaults: dict[str, dict] = {k: dict(v) for k, v in RECOMMENDED.items()}
    for section, values in dash.items():
        defaults.setdefault(section, {}).update(values)
    cfg = load_config(path, defaults=defaults)
    file = tomllib.loads(Path(path).read_text(encoding="utf-8", errors="replace")) if path is not None else {}
    layers = {"file": file, "dashboard": dash, "recommended": RECOMMENDED}
    sources: dict[str, str] = {}
    for section in JobConfig.model_fields:
        seen: set[str] = set()
        used = []
        for name in SOURCES:
            values = layers[name].get(section)
            keys = set(values) if isinstance(values, dict) else set()
            if keys - seen:
                used.append(name)
            seen |= keys
        sources[section] = "+".join(used) or "default"
    return cfg, sources


def open_printer(spec: str, gcode: bytes | None = None, *, key_file: Path | None = None, host=None):
    """Printer connector from ``octoprint://host:port``, ``moonraker://host:port`` or ``virtual[:FILE]``.

    The API key comes from ``key_file`` (``--key-file``), the environment (``LAYERWATCH_OCTOPRINT_KEY``,
    ``LAYERWATCH_MOONRAKER_KEY``), the job file's ``[host]`` section (``host``: :class:`HostSettings`), or,
    with a warning, a ``?key=`` in ``spec`` (see :func:`~layerwatch.monitor.printers.keys.resolve_key`).
    """
    from layerwatch.errors import ConfigError
    from layerwatch.monitor.printers.keys import redact_url, resolve_key, split_url_key

    kind = spec.split("://", 1)[0] if "://" in spec else ""
    if kind in ("octoprint", "moonraker"):
        file = key_file or (Path(host.key_file) if host is not None and host.key_file else None)
        config_key = host.api_key.get_secret_value() if host is not None and host.api_key else None
        key, source = resolve_key(kind, spec, key_file=file, config_key=config_key)
        logging.getLogger("layerwatch.monitor").info("%s API key from: %s", kind, source)
        url = split_url_key(spec)[0]
        if kind == "octoprint":
            from layerwatch.monitor.printers.octoprint import OctoPrintPrinter

            return OctoPrintPrinter(url, key)
        from layerwatch.monitor.printers.moonraker import MoonrakerPrinter

        return MoonrakerPrinter(url, key)
    if spec == "virtual" or spec.startswith("virtual:"):
        from layerwatch.monitor.printers.virtual import VirtualPrinter

        path = spec[8:]
        data = Path(path).read_bytes() if path else gcode
        if data is None:
            raise ConfigError("--printer virtual needs a G-code: virtual:FILE or --gcode FILE.")
        return VirtualPrinter(data, name=Path(path).name if path else "virtual.gcode")
    raise ConfigError(f"unknown --printer {redact_url(spec)!r}; use octoprint://host:port, moonraker://host:port "
                      "or virtual:FILE.")


def monitor(
    printer: Annotated[str, typer.Option("--printer", help="octoprint://host:port | moonraker://host:port | virtual[:FILE] (API key: --key-file, LAYERWATCH_OCTOPRINT_KEY / LAYERWATCH_MOONRAKER_KEY, or [host] in the job file)")] = "virtual",
    key_file: Annotated[Path | None, typer.Option("--key-file", help="File whose first line is the printer host's API key (chmod 600).")] = None,
    camera: Annotated[str, typer.Option("--camera", help="http://...snapshot | http://...stream | file:DIR | /dev/videoN | sim")] = "sim",
    gcode: Annotated[Path | None, typer.Option("--gcode", help="The job's G-code (default: bundled example).")] = None,
    camera_model: Annotated[Path | None, typer.Option("--camera-model", help="camera.toml with intrinsics and pose.")] = None,
    config: Annotated[Path | None, typer.Option("--config", help="Job config TOML (policy, notify...).")] = None,
    history: Annotated[Path | None, typer.Option("--history", help="SQLite history file to record the job in; settings saved there by the dashboard apply (under --config keys).")] = None,
    settle: Annotated[float, typer.Option("--settle", min=0, help="Seconds to wait after the trigger before the photo.")] = 0.0,
    wait_for_verdict: Annotated[bool, typer.Option("--wait-for-verdict", help="Hold the printer until the layer is analysed.")] = False,
    failure: Annotated[str | None, typer.Option("--failure", help="sim camera: inject this failure type.")] = None,
    onset: Annotated[int, typer.Option("--onset", min=1, help="sim camera: first failed layer.")] = 15,
    seed: Annotated[int, typer.Option("--seed", help="sim camera: seed.")] = 1,
    poll: Annotated[float, typer.Option("--poll", min=0.05, max=60.0, help="Printer status poll interval, s; an unreachable host is retried with back-off up to this interval.")] = 0.2,
) -> None:
    """Watch a print until it ends: photo per layer, analysis, pause on a failure (Ctrl-C/SIGTERM stops cleanly)."""
    import dataclasses

    from layerwatch.cli import console
    from layerwatch.errors import ConfigError
    from layerwatch.examples import PART_GCODE
    from layerwatch.gcode import read_toolpath
    from layerwatch.gcode.postprocess import insert_snapshots
    from layerwatch.geometry.camera import CameraModel
    from layerwatch.monitor.cameras import SimCamera, open_camera
    from layerwatch.monitor.notify import Notifier
    from layerwatch.monitor.pipeline import LayerPipeline
    from layerwatch.monitor.policy import PausePolicy
    from layerwatch.monitor.printers.base import parse_trigger
    from layerwatch.monitor.printers.keys import redact_url
    from layerwatch.monitor.service import Monitor

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s %(message)s")
    from layerwatch.examples import PART_CONFIG

    # per key: the job file (--config; no --config and no --gcode: the example part's job file) > the
    # settings saved in the dashboard (--history) > the evaluation's recommended settings > built-in defaults
    from layerwatch.storage.history import History

    job_file = config if config else (PART_CONFIG if gcode is None else None)
    if history is not None:
        with History(history) as saved:
            cfg, sources = monitor_config(job_file, saved)
    else:
        cfg, sources = monitor_config(job_file)
    logging.getLogger("layerwatch.monitor").info(
        "settings from: %s (file %s, dashboard %s)", " ".join(f"{k}={v}" for k, v in sources.items()),
        job_file or "none", history or "none")
    gpath = gcode or PART_GCODE
    data = gpath.read_bytes()
    toolpath = read_toolpath(data)
    if printer.startswith("virtual") and not any(parse_trigger(ln) for ln in data.decode("utf-8", "replace").splitlines()):
        console.print("[dim]G-code has no layerwatch triggers: inserting them (octoprint profile) for the virtual printer[/]")
        data = insert_snapshots(data, cfg.snapshot.model_copy(update={"profile": "octoprint"}), cfg.printer)
    tv = cfg.topview.topview()
    if camera == "sim":
        from layerwatch.geometry.pose import locate_bed
        from layerwatch.simulate import Failure, PrintSimulator, default_camera

        truth = default_camera(tv)
        fails = [Failure(failure, onset=onset, seed=seed)] if failure else []
        sim = PrintSimulator(toolpath, truth, tv, fails, seed=seed)
        cam_src = SimCamera(lambda i: sim.frame(min(i, toolpath.n_layers - 1)).photo, settle_s=settle)
        cam_model = (CameraModel.load(camera_model) if camera_model else
                     locate_bed(dataclasses.replace(truth, rvec=None, tvec=None), sim.frame(0).photo, cfg.markers, tv))
    else:
        if camera_model is None:
            raise ConfigError("--camera-model camera.toml is needed with a real camera; make one with `layerwatch calibrate`.")
        cam_src = open_camera(camera, settle_s=settle)
        cam_model = CameraModel.load(camera_model)
    prn = open_printer(printer, data, key_file=key_file, host=cfg.host)
    hist = job = None
    if history is not None:
        hist = History(history)
        job = hist.start_job(redact_url(printer), gpath, config=cfg)
    mon = Monitor(prn, cam_src, LayerPipeline(toolpath, cam_model, cfg), PausePolicy(cfg.policy),
                  notifier=Notifier(cfg.notify), history=hist, job_id=job,
                  wait_for_verdict=wait_for_verdict or cfg.policy.wait_for_verdict,
                  faults=cfg.faults, frame_quality=cfg.frame_quality)
    console.print(f"monitoring {redact_url(printer)} with camera {redact_url(camera)} ({toolpath.n_layers} layers)")
    try:
        rep = mon.run(install_signals=True, poll_s=poll)
    finally:
        prn.close()
        if hist is not None:
            hist.close()
    lat = rep.latencies_ms
    console.print(f"{len(rep.results)} layers analysed, {rep.pauses} pause(s), {rep.alerts} alert(s); outcome {rep.outcome}")
    if rep.camera_faults or rep.printer_faults:
        console.print(f"faults (never a pause): {rep.camera_faults} unusable frame(s), "
                      f"{rep.printer_faults} failed printer poll(s)")
    for d in rep.decisions:
        if d.stops:
            console.print(f"[bold red]{d.action.upper()}[/] {d.reason}")
    if lat:
        console.print(f"trigger -> pause request: {', '.join(f'{x:.0f} ms' for x in lat)}")


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.command("monitor")(monitor)
