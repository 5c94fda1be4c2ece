"""``layerwatch monitor``: watch a print on OctoPrint, Moonraker or the virtual printer."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Any

import typer
from pydantic import ValidationError

from layerwatch.cli import console
from layerwatch.cli.params import SEED, WRITE_DB, WRITE_DIR, Finite
from layerwatch.cli.pipeline import BED_HELP, PAPER_HELP, scene_baseline
from layerwatch.errors import ConfigError
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.objects import quiet_layers, read_objects
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.monitor.artifacts import ArtifactStore, StoringPipeline
from layerwatch.monitor.follow import CameraSpec, job_camera, run_follow
from layerwatch.monitor.homeassistant import HistoryResults, broker_target, open_bridge
from layerwatch.monitor.hosts import HOST_PRINTERS, open_host_printer, printer_camera
from layerwatch.monitor.notify import Notifier
from layerwatch.monitor.printers.base import parse_trigger
from layerwatch.monitor.printers.keys import read_key_file, redact_url, resolve_key, split_url_key
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter
from layerwatch.monitor.printers.octoprint import OctoPrintPrinter
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor, MonitorReport
from layerwatch.pipeline.config import JobConfig, recommended_config, resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.storage.history import History
from layerwatch.web.settings import SETTINGS_KEY

__all__ = ["register", "monitor_config", "dashboard_settings"]


def dashboard_settings(history) -> dict[str, dict]:
    """The settings the dashboard saved in ``history`` that differ from what it shows unsaved.

    The dashboard stores the whole job config it showed (``PUT``/``PATCH /api/settings``); unsaved, it shows
    the recommended settings (:func:`~layerwatch.pipeline.config.recommended_config`), so a key it never
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

    base = recommended_config().model_dump(mode="json")
    out: dict[str, dict] = {}
    for section, values in cfg.model_dump(mode="json").items():
        changed = {k: v for k, v in values.items() if v != base[section].get(k)}
        if changed:
            out[section] = changed
    return out


def monitor_config(path: Path | None, history=None, *, paper: bool = False):
    """The monitor's job config and where each section's values came from.

    Precedence, per key: the job file's own keys > the dashboard's saved settings (:func:`dashboard_settings`)
    > the evaluation's recommended settings (:data:`layerwatch.pipeline.config.RECOMMENDED`) > the
    sections' built-in defaults.

    Parameters
    ----------
    path : Path or None
        Job config TOML (``--config``, or the bundled example's job file).
    history : History or None
        Database whose dashboard settings apply (``--history``).
    paper : bool
        Leave out the recommended settings (``--paper-settings``).

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
    dash = dashboard_settings(history) if history is not None else {}
    dash.pop("host", None)  # printer credentials come from the job file, the environment or a key file only
    resolved = resolve_config(path, recommended=not paper, dashboard=dash)
    return resolved.config, resolved.section_sources()


def open_printer(spec: str, gcode: bytes | None = None, *, key_file: Path | None = None, host=None):
    """Printer connector from ``octoprint://host:port``, ``moonraker://host:port`` or ``virtual[:FILE]``.

    The API key comes from ``key_file`` (``--key-file``), the environment (``LAYERWATCH_OCTOPRINT_KEY``,
    ``LAYERWATCH_MOONRAKER_KEY``), the job file's ``[host]`` section (``host``: :class:`HostSettings`), or,
    with a warning, a ``?key=`` in ``spec`` (see :func:`~layerwatch.monitor.printers.keys.resolve_key`).
    """
    kind = spec.split("://", 1)[0] if "://" in spec else ""
    if kind in HOST_PRINTERS:
        return open_host_printer(kind, spec, gcode, key_file=key_file, host=host)
    if kind in ("octoprint", "moonraker"):
        file = key_file or (Path(host.key_file) if host is not None and host.key_file else None)
        config_key = host.api_key.get_secret_value() if host is not None and host.api_key else None
        key, source = resolve_key(kind, spec, key_file=file, config_key=config_key)
        logging.getLogger("layerwatch.monitor").info("%s API key from: %s", kind, source)
        url = split_url_key(spec)[0]
        if kind == "octoprint":
            return OctoPrintPrinter(url, key)
        return MoonrakerPrinter(url, key)
    if spec == "virtual" or spec.startswith("virtual:"):
        path = spec[8:]
        data = Path(path).read_bytes() if path else gcode
        if data is None:
            raise ConfigError("--printer virtual needs a G-code: virtual:FILE or --gcode FILE.")
        return VirtualPrinter(data, name=Path(path).name if path else "virtual.gcode")
    raise ConfigError(f"unknown --printer {redact_url(spec)!r}; use octoprint://host:port, moonraker://host:port, "
                      "prusalink://host?user=NAME, bambu://host?serial=SERIAL or virtual:FILE.")


def monitor(
    printer: Annotated[str, typer.Option("--printer", help="octoprint://host:port | moonraker://host:port | prusalink://host?user=NAME | bambu://host?serial=SERIAL | virtual[:FILE] (API key, PrusaLink password or Bambu access code: --key-file, LAYERWATCH_<HOST>_KEY, or [host] in the job file)")] = "virtual",
    key_file: Annotated[Path | None, typer.Option("--key-file", exists=True, dir_okay=False, help="File whose first line is the printer host's API key (chmod 600).")] = None,
    camera: Annotated[str, typer.Option("--camera", help="http://...snapshot | http://...stream | file:DIR | /dev/videoN | printer (PrusaLink's or a Bambu P1/A1's own camera) | sim")] = "sim",
    gcode: Annotated[Path | None, typer.Option("--gcode", exists=True, dir_okay=False, help="The job's G-code (default: downloaded from the OctoPrint/Moonraker host; the bundled example for virtual).")] = None,
    camera_model: Annotated[Path | None, typer.Option("--camera-model", exists=True, dir_okay=False, help="camera.toml with intrinsics and pose.")] = None,
    config: Annotated[Path | None, typer.Option("--config", exists=True, dir_okay=False, help="Job config TOML (policy, notify...).")] = None,
    history: Annotated[Path | None, typer.Option("--history", parser=WRITE_DB, help="SQLite history file to record the job in; settings saved there by the dashboard apply (under --config keys).")] = None,
    settle: Annotated[float, typer.Option("--settle", parser=Finite(0, 60, unit="s"), help="Seconds to wait after the trigger before the photo.")] = 0.0,
    wait_for_verdict: Annotated[bool, typer.Option("--wait-for-verdict", help="Hold the printer until the layer is analysed.")] = False,
    failure: Annotated[str | None, typer.Option("--failure", help="sim camera: inject this failure type.")] = None,
    onset: Annotated[int, typer.Option("--onset", parser=Finite(1, 100_000, integer=True), help="sim camera: first failed layer.")] = 15,
    seed: Annotated[int, typer.Option("--seed", parser=SEED, help="sim camera: seed.")] = 1,
    paper: Annotated[bool, typer.Option("--paper-settings", help=PAPER_HELP)] = False,
    follow: Annotated[bool, typer.Option("--follow", "--service", help="Keep running: pick up every job the OctoPrint/Moonraker host starts, with its own G-code.")] = False,
    images: Annotated[Path | None, typer.Option("--images", parser=WRITE_DIR, help="Folder for each layer's images (default: beside --history).")] = None,
    keep_mb: Annotated[float | None, typer.Option("--keep-mb", parser=Finite(1, 10_000_000, unit="MB"), help="Keep at most this many MB of images; oldest jobs' images deleted first.")] = None,
    keep_jobs: Annotated[int | None, typer.Option("--keep-jobs", parser=Finite(1, 1_000_000, integer=True), help="Keep the images of at most this many jobs.")] = None,
    park_tolerance: Annotated[float, typer.Option("--park-tolerance", parser=Finite(0, 50, unit="mm"), help="Reject frames taken with the head farther than this from the park spot, mm (0: no check).")] = 1.0,
    poll: Annotated[float, typer.Option("--poll", parser=Finite(0.05, 60, unit="s"), help="Printer status poll interval, s; an unreachable host is retried with back-off up to this interval.")] = 0.2,
    bed_photo: Annotated[Path | None, typer.Option("--bed-photo", exists=True, dir_okay=False, help=BED_HELP)] = None,
    homeassistant: Annotated[str | None, typer.Option("--homeassistant", help="mqtt://BROKER[:PORT]?node=ID[&user=NAME] (mqtts://...&ca=FILE): publish state, layer, a%, last overlay and a pause switch to Home Assistant by MQTT discovery (password: LAYERWATCH_MQTT_KEY).")] = None,
) -> None:
    """Watch a print until it ends: photo per layer, analysis, pause on a failure (Ctrl-C/SIGTERM stops cleanly)."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s %(message)s")
    job_file = config if config else (PART_CONFIG if gcode is None and printer.startswith("virtual") else None)
    cfg = _settings(job_file, history, paper)
    _check_inputs(printer, key_file, images)
    spec = CameraSpec(camera, camera_model, settle, failure, onset, seed)
    if homeassistant is not None:
        broker_target(homeassistant)  # a bad URL is a usage error now, not after the printer connected
    if not printer.startswith("virtual") and (follow or gcode is None):  # the job's own G-code, from the host
        prn = open_printer(printer, key_file=key_file, host=cfg.host)
        bridge, seen = _follow_bridge(homeassistant, prn, history, images) if homeassistant else (None, None)
        try:
            done = run_follow(prn, cfg, spec, history=history, images=images, keep_mb=keep_mb, keep_jobs=keep_jobs,
                              park_tolerance_mm=park_tolerance or None, wait_for_verdict=wait_for_verdict,
                              max_jobs=None if follow else 1)
        finally:
            if bridge is not None:
                bridge.close()
            if seen is not None:
                seen.close()
        console.print("; ".join(f"{job.path}: {outcome}" for job, outcome in done) or "no job")
        raise typer.Exit(1 if not follow and any(o in ("not prepared", "error") for _, o in done) else 0)
    if follow:
        raise ConfigError("--follow needs a printer host: --printer octoprint://... or moonraker://...")
    rep = _watch_one(printer, gcode or PART_GCODE, cfg, spec, key_file=key_file, history=history,
                     wait_for_verdict=wait_for_verdict, bed_photo=bed_photo, poll=poll, camera=camera,
                     homeassistant=homeassistant)
    _print_report(rep)


def _follow_bridge(url: str, prn, history: Path | None, images: Path | None):
    """The Home Assistant bridge of ``--follow`` and the history connection it reads the jobs' layers from (or None)."""
    if history is None:
        return open_bridge(url, prn), None
    seen = History(history)
    root = images or history.resolve().parent  # where run_follow's ArtifactStore keeps the overlays
    try:
        return open_bridge(url, prn, results=HistoryResults(seen, root, f"{prn.name}:"), history=seen), seen
    except BaseException:
        seen.close()
        raise


def _settings(job_file: Path | None, history: Path | None, paper: bool) -> JobConfig:
    """The job's settings, logged with where each came from.

    Per key: the job file (--config; no --config and no --gcode: the example part's job file) > the
    settings saved in the dashboard (--history) > the evaluation's recommended settings > built-in defaults.
    """
    if history is not None:
        with History(history) as saved:
            cfg, sources = monitor_config(job_file, saved, paper=paper)
    else:
        cfg, sources = monitor_config(job_file, paper=paper)
    logging.getLogger("layerwatch.monitor").info(
        "settings from: %s (file %s, dashboard %s)", " ".join(f"{k}={v}" for k, v in sources.items()),
        job_file or "none", history or "none")
    return cfg


def _check_inputs(printer: str, key_file: Path | None, images: Path | None) -> None:
    """Refuse now (one line, exit 2), not at the first layer: a key file for the virtual printer or one
    that is empty, not a key or readable by everyone; an unusable --images folder."""
    if key_file is not None:
        if printer.startswith("virtual"):
            raise ConfigError("--key-file is for octoprint:// and moonraker:// printers; the virtual printer needs no key.")
        read_key_file(key_file)
    if images is not None:
        images.mkdir(parents=True, exist_ok=True)


def _watch_one(printer: str, gpath: Path, cfg: JobConfig, spec: CameraSpec, *, key_file: Path | None,
               history: Path | None, wait_for_verdict: bool, bed_photo: Path | None, poll: float,
               camera: str, homeassistant: str | None = None) -> MonitorReport:
    """Monitor one job whose G-code is ``gpath`` (local file) until it ends; the printer and history closed after."""
    data = gpath.read_bytes()
    toolpath = read_toolpath(data)
    objects = read_objects(data, toolpath)  # the plate's labelled objects: cancel_object cancels one of them
    if printer.startswith("virtual") and not any(parse_trigger(ln) for ln in data.decode("utf-8", "replace").splitlines()):
        console.print("[dim]G-code has no layerwatch triggers: inserting them (octoprint profile) for the virtual printer[/]")
        data = insert_snapshots(data, cfg.snapshot.model_copy(update={"profile": "octoprint"}), cfg.printer)

    prn = open_printer(printer, data, key_file=key_file, host=cfg.host)
    try:
        cam_src, cam_model = printer_camera(prn, spec) if camera == "printer" else job_camera(spec, toolpath, cfg)
    except BaseException:
        prn.close()
        raise
    hist = job = bridge = None
    if history is not None:
        hist = History(history)
        job = hist.start_job(redact_url(printer), gpath, config=cfg)
    bed = scene_baseline(cfg, cam_model, bed_photo)  # None: the first accepted photo is the scene's start
    pipe: Any = LayerPipeline(toolpath, cam_model, cfg, bed_photo=bed)
    if homeassistant and history is not None and job is not None:  # Home Assistant's image: the stored overlays
        pipe = StoringPipeline(pipe, ArtifactStore(history.resolve().parent), job)
    mon = Monitor(prn, cam_src, pipe, PausePolicy(cfg.policy),
                  notifier=Notifier(cfg.notify), history=hist, job_id=job,
                  wait_for_verdict=wait_for_verdict or cfg.policy.wait_for_verdict,
                  faults=cfg.faults, frame_quality=cfg.frame_quality, objects=objects,
                  quiet_layers=quiet_layers(toolpath, objects))
    if homeassistant:
        bridge = open_bridge(homeassistant, prn, monitor=mon, history=hist, job_id=job)
    console.print(f"monitoring {redact_url(printer)} with camera {redact_url(camera)} ({toolpath.n_layers} layers)")
    try:
        return mon.run(install_signals=True, poll_s=poll)
    finally:
        if bridge is not None:
            bridge.close()
        prn.close()
        if hist is not None:
            hist.close()


def _print_report(rep: MonitorReport) -> None:
    """One summary line per job, the faults (never a pause), each stop and the trigger-to-pause latencies."""
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
