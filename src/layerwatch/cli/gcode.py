"""CLI verbs for the gcode stage: ``layerwatch gcode info|prepare``."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn
from rich.table import Table

from layerwatch.cli import console, err_console
from layerwatch.cli.params import WRITE_FILE, Finite
from layerwatch.errors import ConfigError, GcodeError
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.bed import bed_from_gcode, parse_bed, parse_xy
from layerwatch.gcode.reader import load_bytes
from layerwatch.gcode.summary import info_dict

__all__ = ["register"]

gcode_app = typer.Typer(
    name="gcode", help="Read G-code into layers; insert snapshot blocks.", no_args_is_help=True
)

_PROFILES = ("paper", "octoprint", "klipper", "timelapse", "m240")


#: files above this size get a progress bar: about a second of parsing (the reader does ~200 MB/s)
PROGRESS_BAR_BYTES = 200_000_000


def _read_with_progress(path: Path, filament_diameter: float | None = None):
    big = path.is_file() and path.stat().st_size > PROGRESS_BAR_BYTES
    if not big:
        return read_toolpath(path, filament_diameter=filament_diameter)
    with Progress(
        TextColumn("parsing"), BarColumn(), DownloadColumn(), console=err_console, transient=True
    ) as bar:
        task = bar.add_task("parse", total=path.stat().st_size)
        return read_toolpath(path, filament_diameter=filament_diameter,
                             progress=lambda done, total: bar.update(task, completed=done, total=total))


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, (list, tuple)):
        return " .. ".join(_fmt(x) for x in v) if len(v) == 2 else ", ".join(_fmt(x) for x in v)
    return f"{v:g}" if isinstance(v, float) else str(v)


#: (label, key in the reading, key in the statements)
_ROWS = (
    ("generator", "generator", None),
    ("layers", "layers", "layer_count"),
    ("detection", "detection", None),
    ("Z range (mm)", "z_range_mm", "max_z"),
    ("first layer Z (mm)", "first_layer_z_mm", "first_layer_height"),
    ("layer height (mm)", "median_layer_height_mm", "layer_height"),
    ("segments", "segments", None),
    ("filament, E words (mm)", "filament_commanded_mm", "filament_mm"),
    ("filament, E words (cm3)", "filament_commanded_cm3", "filament_cm3"),
    ("filament fed, M221 + flushes (mm)", "filament_fed_mm", None),
    ("filament diameter (mm)", "filament_diameter_mm", "filament_diameter"),
    ("first layer box (mm)", "first_layer_box_mm", "first_layer_box"),
    ("part bounds (mm)", "part_bounds_mm", "print_box"),
)


@gcode_app.command("info")
def info(
    file: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="A .gcode, .bgcode or FlashForge .gx file.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the reading and the file's statements as JSON.")] = False,
    filament_diameter: Annotated[
        float | None,
        typer.Option("--filament-diameter", parser=Finite(0.5, 5, unit="mm"),
                     help="Filament diameter, mm (default: the file's, else 1.75; 2.85 for UltiGCode)."),
    ] = None,
) -> None:
    """Print what the reader finds next to what the file states, with a warning where they disagree."""
    tp = _read_with_progress(file, filament_diameter)
    if tp.n_layers == 0 and not _has_moves(file):  # no move at all: not G-code (CNC files are still described)
        raise GcodeError(f"{file.name} has no G-code moves: not a G-code file; pass the file your slicer exported.")
    doc = info_dict(tp)
    if as_json:
        print(json.dumps(doc, indent=1))
        return
    table = Table(title=f"{file.name}")
    table.add_column("field", style="bold")
    table.add_column("read")
    table.add_column("file states")
    stated = doc["statements"] or {}
    for label, rkey, skey in _ROWS:
        table.add_row(label, _fmt(doc["reading"][rkey]), _fmt(stated.get(skey)) if skey else "")
    console.print(table)
    if tp.volumetric:
        console.print(f"E words are volumes (mm^3): converted to lengths with {tp.filament_diameter:g} mm filament "
                      "(--filament-diameter to change)")
    for note in stated.get("notes", []):
        err_console.print(f"note: {note}", highlight=False)
    for d in doc["disagreements"]:
        err_console.print(f"[yellow]warning:[/] the file's statement disagrees: {d}", highlight=False)
    for w in tp.warnings:
        err_console.print(f"[yellow]warning:[/] {w}", highlight=False)


def _has_moves(file: Path, limit: int = 1 << 20) -> bool:
    """True when the file's first ``limit`` bytes hold a G0-G3 move (binary .bgcode counts as G-code)."""
    with open(file, "rb") as fh:
        head = fh.read(limit)
    return head.startswith(b"GCDE") or re.search(rb"(?m)^[ \t]*[Gg]0*[0-3](?![0-9.])", head) is not None


_OPTION_OF = {"every_n_layers": "--every", "lift_mm": "--lift", "retract_mm": "--retract", "park_xy_mm": "--park",
              "settle_ms": "--dwell-ms", "hold_s": "--hold"}


@gcode_app.command("prepare")
def prepare(
    file: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="Input .gcode (or .bgcode) file.")],
    output: Annotated[Path, typer.Option("-o", "--output", parser=WRITE_FILE, help="Where to write the new (ASCII) G-code.")],
    profile: Annotated[str, typer.Option("--profile", "-p", help="|".join(_PROFILES))] = "octoprint",
    every: Annotated[int, typer.Option("--every", parser=Finite(1, 100_000, integer=True), help="Snapshot after every Nth layer.")] = 1,
    lift: Annotated[float, typer.Option("--lift", parser=Finite(0, 100, unit="mm"), help="Z lift for the photo, mm.")] = 5.0,
    retract: Annotated[float | None, typer.Option(
        "--retract", parser=Finite(0, 20, unit="mm"), help="Retraction held during the photo, mm (default: the file's retract_length, else 1)."
    )] = None,
    park: Annotated[str, typer.Option(
        "--park", help="Park 'X,Y' in the file's bed mm (default: a bed corner away from the print).")] = "",
    bed: Annotated[str, typer.Option(
        "--bed", help="Bed 'WxH', 'WxHxZ' or polygon 'x,y;x,y;...' mm (default: the bed the file states).")] = "",
    firmware: Annotated[str, typer.Option(
        "--firmware", help="marlin|klipper|reprap (default: the file's gcode_flavor).")] = "",
    dwell_ms: Annotated[int, typer.Option("--dwell-ms", parser=Finite(100, 60_000, integer=True, unit="ms"), help="Dwell at the park spot after the trigger, ms.")] = 1000,
    hold: Annotated[float, typer.Option(
        "--hold", parser=Finite(0.5, 120, unit="s"), help="klipper profile: longest wait for the host's frame, s.")] = 10.0,
) -> None:
    """Insert a snapshot block (paper Table 1) after every (Nth) layer, parked on the file's bed."""
    # imported here, not at the top: pydantic and the firmware model take ~0.15 s to import, which
    # `gcode info` (target: 0.5 s cold on a 20 MB file, issue 20) does not need
    import pydantic

    from layerwatch.gcode.settings import SnapshotSettings
    from layerwatch.gcode.snapshot import prepare_gcode

    if profile not in _PROFILES:
        raise ConfigError(f"unknown profile {profile!r}; use one of {', '.join(_PROFILES)}.")
    if firmware and firmware not in ("marlin", "klipper", "reprap"):
        raise ConfigError(f"--firmware {firmware!r}: use marlin, klipper or reprap.")
    values: dict[str, Any] = {"profile": profile, "every_n_layers": every, "lift_mm": lift, "settle_ms": dwell_ms, "hold_s": hold,
              "park_xy_mm": parse_xy(park, "--park") if park else None}
    if retract is not None:
        values["retract_mm"] = retract
    try:
        snap = SnapshotSettings(**values)
    except pydantic.ValidationError as exc:
        err = exc.errors()[0]
        key = str(err["loc"][0]) if err["loc"] else ""
        raise ConfigError(f"{_OPTION_OF.get(key, key)}: {err['msg']}.") from None
    data, _name = load_bytes(file)
    if not bed and bed_from_gcode(data) is None:
        raise ConfigError(f"{file.name} does not say which bed it was sliced for; pass --bed WxH (e.g. 220x220) "
                          "or a polygon 'x,y;x,y;...' in the file's coordinates.")
    result = prepare_gcode(data, snap, bed=parse_bed(bed) if bed else None, firmware=firmware or None)
    if result.blocks == 0:
        raise GcodeError(f"{file}: no layer to put a snapshot after (--every {every}); pass the G-code your slicer exported.")
    try:
        output.write_bytes(result.data)
    except OSError as exc:
        raise GcodeError(f"{output}: cannot write ({exc.strerror}); choose another -o path.") from exc
    console.print(f"wrote {output} with {result.blocks} snapshot block(s), profile {profile}", highlight=False)
    for note in result.notes:
        err_console.print(f"  {note}", highlight=False, markup=False)
    if profile == "klipper":
        console.print("Klipper: run `layerwatch klipper-config > layerwatch.cfg` and add [include layerwatch.cfg] "
                      "to printer.cfg.", highlight=False, markup=False)


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.add_typer(gcode_app, name="gcode")
