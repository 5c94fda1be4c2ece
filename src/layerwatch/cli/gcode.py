"""CLI verbs for the gcode stage: ``layerwatch gcode info|prepare``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from layerwatch.cli.params import WRITE_FILE, Finite, numbers

__all__ = ["register"]

gcode_app = typer.Typer(
    name="gcode", help="Read G-code into layers; insert snapshot blocks.", no_args_is_help=True
)

_PROFILES = ("paper", "octoprint", "klipper", "timelapse", "m240")


def _read_with_progress(path: Path):
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn

    from layerwatch.cli import err_console
    from layerwatch.gcode import read_toolpath

    big = path.is_file() and path.stat().st_size > 5_000_000
    if not big:
        return read_toolpath(path)
    with Progress(
        TextColumn("parsing"), BarColumn(), DownloadColumn(), console=err_console, transient=True
    ) as bar:
        task = bar.add_task("parse", total=path.stat().st_size)
        return read_toolpath(path, progress=lambda done, total: bar.update(task, completed=done, total=total))


@gcode_app.command("info")
def info(file: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="A .gcode (or .bgcode) file.")]) -> None:
    """Print layers, Z range, detection method, extrusion length and bounds."""
    from rich.table import Table

    from layerwatch.cli import console, err_console

    tp = _read_with_progress(file)
    if tp.n_layers == 0 and not _has_moves(file):  # no move at all: not G-code (CNC files are still described)
        from layerwatch.errors import GcodeError

        raise GcodeError(f"{file.name} has no G-code moves: not a G-code file; pass the file your slicer exported.")
    table = Table(title=f"{file.name}", show_header=False)
    table.add_column("field", style="bold")
    table.add_column("value")
    zs = [lay.z for lay in tp.layers]
    table.add_row("slicer", tp.slicer or "unknown")
    table.add_row("layers", str(tp.n_layers))
    table.add_row("detection", tp.detection)
    table.add_row("Z range (mm)", f"{min(zs):.3f} .. {max(zs):.3f}" if zs else "-")
    if tp.n_layers:
        h = sorted(lay.height for lay in tp.layers)
        table.add_row("layer height (mm)", f"{h[len(h) // 2]:.3f} (median)")
    table.add_row("segments", str(tp.n_segments))
    table.add_row("extrusion (mm of filament)", f"{tp.extrusion_mm:.1f}")
    table.add_row("filament diameter (mm)", f"{tp.filament_diameter:g}")
    b = tp.bounds
    table.add_row("bounds X (mm)", f"{b[0]:.2f} .. {b[2]:.2f}")
    table.add_row("bounds Y (mm)", f"{b[1]:.2f} .. {b[3]:.2f}")
    console.print(table)
    for w in tp.warnings:
        err_console.print(f"[yellow]warning:[/] {w}", highlight=False)


def _has_moves(file: Path, limit: int = 1 << 20) -> bool:
    """True when the file's first ``limit`` bytes hold a G0-G3 move (binary .bgcode counts as G-code)."""
    import re

    with open(file, "rb") as fh:
        head = fh.read(limit)
    return head.startswith(b"GCDE") or re.search(rb"(?m)^[ \t]*[Gg]0*[0-3](?![0-9.])", head) is not None


@gcode_app.command("prepare")
def prepare(
    file: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="Input .gcode file.")],
    output: Annotated[Path, typer.Option("-o", "--output", parser=WRITE_FILE, help="Where to write the new G-code.")],
    profile: Annotated[str | None, typer.Option("--profile", "-p", help="|".join(_PROFILES) + " (default octoprint).")] = None,
    every: Annotated[int | None, typer.Option("--every", parser=Finite(1, 100_000, integer=True), help="Snapshot after every Nth layer (default 1).")] = None,
    lift: Annotated[float | None, typer.Option("--lift", parser=Finite(0, 100, unit="mm"), help="Z lift for the photo, mm (default 5).")] = None,
    retract: Annotated[float | None, typer.Option("--retract", parser=Finite(0, 20, unit="mm"), help="Retraction before parking, mm (default 1).")] = None,
    park: Annotated[str, typer.Option("--park", help="Park 'X,Y' in mm (default: back corner).")] = "",
    volume: Annotated[str, typer.Option("--volume", help="Printer volume 'X,Y,Z' max, mm.")] = "",
    config: Annotated[Path | None, typer.Option("--config", "-c", exists=True, dir_okay=False, help="Job config TOML ([snapshot], [printer]); the options above win over it.")] = None,
) -> None:
    """Insert a snapshot block (paper Table 1) after every (Nth) layer."""
    from layerwatch.cli import console
    from layerwatch.errors import ConfigError, GcodeError
    from layerwatch.gcode.postprocess import insert_snapshots
    from layerwatch.gcode.reader import load_bytes
    from layerwatch.pipeline.config import resolve_config

    if profile is not None and profile not in _PROFILES:
        raise ConfigError(f"unknown profile {profile!r}; use one of {', '.join(_PROFILES)}.")
    park_xy = numbers(park, 2, "--park", Finite(unit="mm"), "200,200")
    vol = numbers(volume, 3, "--volume", Finite(0, 10_000, lo_open=True, unit="mm"), "220,220,250")
    given = {"profile": profile, "every_n_layers": every, "lift_mm": lift, "retract_mm": retract, "park_xy_mm": park_xy}
    flags = {"snapshot": {k: v for k, v in given.items() if v is not None}}
    if vol is not None:
        flags["printer"] = {"volume_max_mm": vol}
    cfg = resolve_config(config, flags=flags).config
    data, _name = load_bytes(file)
    out = insert_snapshots(data, cfg.snapshot, cfg.printer)
    if b"; layerwatch snapshot block end" not in out:
        raise GcodeError(f"{file}: no layer to put a snapshot after (--every {cfg.snapshot.every_n_layers}); pass the G-code your slicer exported.")
    try:
        output.write_bytes(out)
    except OSError as exc:
        raise GcodeError(f"{output}: cannot write ({exc.strerror}); choose another -o path.") from exc
    n = out.count(b"; layerwatch snapshot block end")
    console.print(f"wrote {output} with {n} snapshot block(s), profile {cfg.snapshot.profile}")
    if cfg.snapshot.profile == "klipper":
        console.print("Klipper: add the LAYERWATCH_SNAPSHOT macro (layerwatch.gcode.postprocess.KLIPPER_MACRO).")


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.add_typer(gcode_app, name="gcode")
