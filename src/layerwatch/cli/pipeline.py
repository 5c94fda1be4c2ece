"""CLI verbs of the offline pipeline: ``analyze``, ``simulate`` and ``evaluate``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import cv2
import typer
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from layerwatch.cli import console, err_console
from layerwatch.cli.params import SEED, WRITE_DIR, Finite
from layerwatch.errors import CalibrationError, ConfigError, GcodeError
from layerwatch.evaluate.harness import clean_false_alarms, run_evaluation
from layerwatch.evaluate.offline import run_offline
from layerwatch.evaluate.report import rich_table, write_report
from layerwatch.evaluate.summary import at_setting, summarize
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.pipeline.config import observed_square, resolve_config
from layerwatch.pipeline.scene import load_bed_photo
from layerwatch.simulate import Failure, PrintSimulator, SimSettings, default_camera, save_frame

__all__ = ["register"]


def _progress():
    cols = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    return Progress(*cols, console=console, transient=True)


def _toolpath(gcode: Path | None):
    """The job's toolpath (default: the bundled example part)."""
    if gcode is not None and not gcode.is_file():
        raise GcodeError(f"G-code file {gcode} not found; check the path.")
    tp = read_toolpath(gcode or PART_GCODE)
    if tp.n_layers == 0:
        raise GcodeError(f"{gcode} has no printed layers; pass the G-code your slicer exported.")
    return tp


def job_settings(config: Path | None, gcode: Path | None, tp=None, *, paper: bool = False,
                 flags: dict[str, dict] | None = None):
    """The verbs' settings through :func:`~layerwatch.pipeline.config.resolve_config`.

    The job file is ``config``, else the bundled example's job file when no
    G-code is given either; with no job file the observed square is centred on
    the part (source ``gcode``). ``paper`` leaves out the recommended settings
    (``--paper-settings``). Returns the :class:`~layerwatch.pipeline.config.ResolvedConfig`.
    """
    path = config if config is not None else (PART_CONFIG if gcode is None else None)
    derived = observed_square(tp.bounds) if path is None and tp is not None else None
    return resolve_config(path, recommended=not paper, gcode=derived, flags=flags)


#: the help of ``--paper-settings``, the same on every verb
PAPER_HELP = ("Leave out the evaluation's recommended settings: the job file over the paper's defaults "
              "(cosine, T_S 0.7, 5 mm margin, pause a% > 10 %).")


#: the help of ``--bed-photo``, the same on every verb
BED_HELP = ("Photo of the empty bed from the monitoring camera (default: the one `calibrate --markers` kept "
            "with the camera model): the scene channel's first expected appearance.")


def scene_baseline(cfg, camera, bed_photo: Path | None):
    """The empty-bed photo for the scene channel (``--bed-photo`` or the camera's), saying what is missing.

    ``None`` when the channel is off (``--paper-settings``) or there is no usable bed photo.
    """
    if not cfg.scene.enabled:
        if bed_photo is not None:
            console.print("[yellow]note:[/] the scene channel is off ([scene] enabled = false); --bed-photo is not used")
        return None
    path = bed_photo if bed_photo is not None else camera.bed_photo
    photo, note = load_bed_photo(path, camera, given=bed_photo is not None)
    if note:
        console.print(f"[yellow]note:[/] {escape(note)}")
    return photo


def analyze(
    photos: Annotated[list[Path], typer.Argument(exists=True, dir_okay=False, help="Layer photos, named by layer (layer_0012.png) or in order.")],
    gcode: Annotated[Path, typer.Option("--gcode", "-g", exists=True, dir_okay=False, help="The job's G-code.")],
    camera: Annotated[Path, typer.Option("--camera", exists=True, dir_okay=False, help="camera.toml with intrinsics and bed pose (layerwatch calibrate).")],
    out: Annotated[Path, typer.Option("-o", "--out", parser=WRITE_DIR, help="Results folder (re-running resumes).")] = Path("results"),
    config: Annotated[Path | None, typer.Option("--config", "-c", exists=True, dir_okay=False, help="Job config TOML.")] = None,
    cache: Annotated[Path | None, typer.Option("--cache", parser=WRITE_DIR, help="Reference cache folder.")] = None,
    paper: Annotated[bool, typer.Option("--paper-settings", help=PAPER_HELP)] = False,
    bed_photo: Annotated[Path | None, typer.Option("--bed-photo", dir_okay=False, help=BED_HELP)] = None,
) -> None:
    """Analyse photos of a print layer by layer: warp, reference, HOG comparison, scene, pause decision.

    Exits 1 when no photo could be analysed.
    """
    if not camera.is_file():
        raise CalibrationError(f"camera file {camera} not found; run `layerwatch calibrate` first.")
    tp = _toolpath(gcode)
    cfg = job_settings(config, gcode, tp, paper=paper).config
    cam = CameraModel.load(camera)
    bed = scene_baseline(cfg, cam, bed_photo)
    with _progress() as bar:
        task = bar.add_task("analysing", total=len(photos))
        run = run_offline(tp, cam, cfg, photos, out, cache_dir=cache, bed_photo=bed,
                          progress=lambda d, n, text: bar.update(task, completed=d, total=n, description=text))
    for p in run.problems:
        console.print(f"[yellow]warning:[/] {escape(p)}")
    if run.missing:
        console.print(f"[yellow]warning:[/] no photo for layer(s) {', '.join(map(str, run.missing))}")
    ok = sum(r.status == "ok" for r in run.results.values())
    console.print(f"{ok} of {len(run.results)} layers analysed ({run.reused} reused) -> {out}/summary.md")
    if ok == 0:  # exit 1: the job failed, nothing was analysed (the warnings above say why)
        err_console.print("[bold red]error:[/] no layer was analysed; see the warnings above.")
        raise typer.Exit(1)
    if run.paused_at is not None:
        console.print(f"[bold red]would have paused at layer {run.paused_at}[/]: {escape(run.reason)}")
    else:
        console.print("no layer would have paused the print")


PhotorealOpt = Annotated[bool, typer.Option("--photoreal", help="Render the photos with Blender Cycles (needs `blender`; "
                                           "seconds a photo) instead of the simulator's ray caster.")]
SamplesOpt = Annotated[int, typer.Option("--samples", parser=Finite(1, 4096, integer=True), help="Cycles samples per "
                                         "pixel with --photoreal.")]


def _sim_settings(photoreal: bool, samples: int) -> SimSettings | None:
    """The simulator's settings for ``--photoreal`` (checked for Blender now, not at the first photo)."""
    if not photoreal:
        return None
    from layerwatch.render.blender import find_blender

    find_blender()
    return SimSettings(renderer="blender", blender_samples=samples)


def simulate(
    gcode: Annotated[Path | None, typer.Option("--gcode", "-g", exists=True, dir_okay=False, help="G-code (default: the bundled example part).")] = None,
    failure: Annotated[list[str] | None, typer.Option("--failure", "-f", help="TYPE@LAYER[:SIZE_MM][/beside], repeatable, "
                                                       "e.g. spaghetti@15, layer_shift@10:3 or foreign_body@8:10/beside "
                                                       "(on the bed beside the part).")] = None,
    out: Annotated[Path, typer.Option("-o", "--out", parser=WRITE_DIR, help="Output folder (photos, truth masks, camera.toml).")] = Path("sim"),
    layers: Annotated[int | None, typer.Option("--layers", "-n", parser=Finite(1, 100_000, integer=True), help="Only the first N layers.")] = None,
    seed: Annotated[int, typer.Option("--seed", parser=SEED, help="Simulation seed.")] = 0,
    width: Annotated[int, typer.Option("--width", parser=Finite(64, 8192, integer=True, unit="px"), help="Photo width px (16:9).")] = 1280,
    config: Annotated[Path | None, typer.Option("--config", "-c", exists=True, dir_okay=False, help="Job config TOML ([topview]).")] = None,
    photoreal: PhotorealOpt = False,
    samples: SamplesOpt = 32,
) -> None:
    """Simulate camera photos of a print (with failures and ground-truth masks) and the empty bed (bed.png)."""
    fails = []
    for spec in failure or []:
        try:
            kind, rest = spec.split("@", 1)
            rest, slash, place = rest.partition("/")
            onset, _, size = rest.partition(":")
            opts: dict[str, Any] = {}  # only what the spec names: Failure's defaults otherwise
            if size:
                opts["size_mm"] = float(size)
            if slash:
                opts["place"] = place.strip()
            fails.append(Failure(kind.strip(), onset=int(onset), **opts))
        except ValueError:
            raise ConfigError(f"--failure {spec!r} is not TYPE@LAYER[:SIZE_MM][/beside]; e.g. spaghetti@15.") from None
    sim_settings = _sim_settings(photoreal, samples)
    tp = _toolpath(gcode)
    cfg = job_settings(config, gcode, tp).config
    cam = default_camera(cfg.topview.topview(), image_size=(width, int(round(width * 9 / 16))))
    tv = cfg.for_camera(cam).topview.topview()  # truth masks in the top view analyze will use
    out.mkdir(parents=True, exist_ok=True)
    sim = PrintSimulator(tp, cam, tv, fails, seed=seed, settings=sim_settings)
    cv2.imwrite(str(out / "bed.png"), sim.bed_photo())  # the empty bed, kept with the camera as calibrate does
    cam.bed_photo = str(out / "bed.png")
    cam.save(out / "camera.toml")
    n = tp.n_layers if layers is None else min(layers, tp.n_layers)
    with _progress() as bar:
        task = bar.add_task("simulating", total=n)
        for i in range(n):
            fr = sim.frame(i)
            save_frame(fr, out)
            bar.update(task, advance=1, description=f"layer {fr.layer}")
    console.print(f"wrote {n} photos (+ truth masks where failed), the empty bed (bed.png) and camera.toml to {out}")


def evaluate(
    gcode: Annotated[Path | None, typer.Option("--gcode", "-g", exists=True, dir_okay=False, help="G-code (default: the bundled example part).")] = None,
    layers: Annotated[int, typer.Option("--layers", "-n", parser=Finite(14, 100_000, integer=True), help="Approximate number of simulated layer photos.")] = 200,
    out: Annotated[Path, typer.Option("-o", "--out", parser=WRITE_DIR, help="Report folder.")] = Path("docs/evaluation"),
    seed: Annotated[int, typer.Option("--seed", parser=SEED, help="Simulation seed.")] = 0,
    width: Annotated[int, typer.Option("--width", parser=Finite(64, 8192, integer=True, unit="px"), help="Photo width px (16:9).")] = 1280,
    config: Annotated[Path | None, typer.Option("--config", "-c", exists=True, dir_okay=False, help="Job config TOML.")] = None,
    margin: Annotated[float | None, typer.Option("--margin-mm", parser=Finite(0, 100, unit="mm"), help="Footprint margin of the considered blocks.")] = None,
    match_camera: Annotated[bool, typer.Option("--match-camera", help="Camera-matched references.")] = False,
    clean_layers: Annotated[int, typer.Option("--clean-layers", parser=Finite(0, 100_000, integer=True), help="Also simulate about N layers of whole "
                                              "clean prints and count false alarms of the configured setting.")] = 0,
    paper: Annotated[bool, typer.Option("--paper-settings", help=PAPER_HELP)] = False,
    beside: Annotated[float, typer.Option("--beside-share", parser=Finite(0, 1), help="Share of the foreign bodies "
                                          "and spaghetti placed on the bed beside the part.")] = 0.0,
    workers: Annotated[int, typer.Option("--workers", "-j", parser=Finite(0, 1024, integer=True), help="Worker processes "
                                         "(0 = all cores); the report is the same for any number.")] = 1,
    photoreal: PhotorealOpt = False,
    samples: SamplesOpt = 32,
) -> None:
    """Score the twelve measures on simulated failures; write a Markdown report with charts."""
    sim_settings = _sim_settings(photoreal, samples)
    tp = _toolpath(gcode)
    flags = {"analysis": {"footprint_margin_mm": margin}} if margin is not None else None
    cfg = job_settings(config, gcode, tp, paper=paper, flags=flags).config
    cam = default_camera(cfg.topview.topview(), image_size=(width, int(round(width * 9 / 16))))
    with _progress() as bar:
        task = bar.add_task("simulating + scoring", total=layers)
        data = run_evaluation(tp, cfg, cam, n_layers=layers, seed=seed, match_camera=match_camera, beside_share=beside,
                              progress=lambda d, n: bar.update(task, completed=d, total=n), workers=workers,
                              sim_settings=sim_settings)
    s = summarize(data)
    notes = [f"{e}" for e in data.errors]
    clean_run = None
    if clean_layers:  # whole clean prints under the setting a job runs with (what the monitor would do)
        with _progress() as bar:
            task = bar.add_task("clean prints (false alarms)", total=clean_layers)
            clean_run = clean_false_alarms(tp, cfg, cam, clean_layers, float(cfg.policy.pause_ratio),
                                           consecutive=cfg.policy.consecutive_layers, workers=workers,
                                           progress=lambda d, n: bar.update(task, completed=d, total=n),
                                           sim_settings=sim_settings)
        clean_run.pop("a", None)
        clean_run["setting"] = (f"{cfg.analysis.metric} T_S {cfg.analysis.threshold:.2f}, pause a% > "
                                f"{100 * cfg.policy.pause_ratio:.1f} % on {cfg.policy.consecutive_layers} layers")
    configured = at_setting(data, cfg.analysis.metric, cfg.analysis.threshold, cfg.policy.pause_ratio)
    path = write_report(s, out, data.setup, data.seconds, notes=notes, clean_run=clean_run, configured=configured)
    console.print(rich_table(s))
    if configured:
        console.print(f"configured: {configured['metric']} T_S={configured['threshold']:.2f}, pause a% > "
                      f"{100 * configured['pause_ratio']:.1f} %: clean layers above it {configured['clean_above']}/"
                      f"{configured['n_clean']}; AUROC " + ", ".join(
                          f"{t} {v[1]:.2f}" for t, v in configured["types"].items()))
        if "whole_view" in configured:
            console.print("with the scene channel (whole view): AUROC " + ", ".join(
                f"{t} {v:.2f}" for t, v in configured["whole_view"].items())
                + f"; clean layers with a change beside the print {configured['clean_outside']}/{configured['n_clean']}")
    r = s.rec_metric
    console.print(f"recommended: {s.metrics[r]} T_S={s.thresholds[s.rec_t]:.2f}, pause a% > "
                  f"{100 * s.pause_ratio[r]:.1f} %; report {path} ({data.seconds:.0f} s)")


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.command("analyze")(analyze)
    app.command("simulate")(simulate)
    app.command("evaluate")(evaluate)
