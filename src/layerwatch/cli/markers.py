"""``layerwatch markers``: a printable sheet of the bed markers that ``calibrate --markers`` looks for."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from layerwatch.cli import console
from layerwatch.cli.params import Finite
from layerwatch.errors import ConfigError
from layerwatch.geometry.marker_sheet import parse_pair, plan_layout, write_sheet

__all__ = ["register"]


def markers(
    bed: Annotated[str, typer.Option("--bed", help="Bed width x depth in mm, e.g. 220x220.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Sheet to write: .pdf, .svg or .png (printed at 1:1).")],
    kind: Annotated[str, typer.Option("--kind", help="dots (white dots on black squares) or aruco (ArUco tags).")] = "dots",
    side: Annotated[float | None, typer.Option("--side", parser=Finite(0, 2000, lo_open=True, unit="mm"), help="Side of the square the four marks span, mm "
                                               "(default: the 90 mm observed square).")] = None,
    center: Annotated[str | None, typer.Option("--center", help="Centre of that square in bed mm, X,Y "
                                               "(default: the bed's centre).")] = None,
    origin: Annotated[str, typer.Option("--origin", help="G-code coordinates of the bed's front-left corner, X,Y "
                                        "(e.g. -110,-110 when the origin is the bed centre).")] = "0,0",
    size: Annotated[float | None, typer.Option("--size", parser=Finite(0, 200, lo_open=True, unit="mm"), help="Dot diameter (default 6) or tag side (default 25), mm.")] = None,
    dictionary: Annotated[str, typer.Option("--dictionary", help="ArUco dictionary (--kind aruco).")] = "DICT_4X4_50",
    paper: Annotated[str, typer.Option("--paper", help="Paper size: a4 or letter.")] = "a4",
    tiles: Annotated[bool, typer.Option("--tiles", help="One page per mark (marks farther apart than a page).")] = False,
    dpi: Annotated[float, typer.Option("--dpi", parser=Finite(72, 1200, unit="dpi"), help="PNG resolution, dots per inch.")] = 300.0,
    config_out: Annotated[Path | None, typer.Option("--config-out", help="Also write a job config (TOML) with the "
                                                    "topview and markers sections of this layout (new file).")] = None,
) -> None:
    """Write a printable marker sheet (1:1) for `layerwatch calibrate --markers`, with each mark's bed coordinates."""
    if config_out is not None and config_out.exists():
        raise ConfigError(f"--config-out {config_out} already exists; add the lines printed by this command to it "
                          "by hand or choose a new file name.")
    layout = plan_layout(parse_pair(bed, "--bed", "x"), kind=kind, side_mm=side,
                         center_mm=parse_pair(center, "--center") if center is not None else None,
                         bed_min_mm=parse_pair(origin, "--origin"), size_mm=size, dictionary=dictionary)
    written = write_sheet(layout, output, paper=paper, tiles=tiles, dpi=dpi)
    files = sorted({str(p) for p, _ in written})
    scale = f"{dpi:g} dpi, print at {dpi:g} dpi" if output.suffix.lower() == ".png" else "print at 100 %"
    console.print(f"marker sheet ({len(written)} page{'s' if len(written) > 1 else ''}, {paper}, {scale}): "
                  f"{', '.join(files)}", highlight=False, soft_wrap=True)
    for i in range(4):
        x, y = layout.positions_mm[i]
        console.print(f"  {layout.label(i)}   (check: G1 X{x:g} Y{y:g} puts the nozzle over it)", highlight=False, soft_wrap=True)
    toml = layout.config_toml()
    if config_out is not None:
        try:
            config_out.write_text(toml, encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"cannot write --config-out {config_out}: {exc.strerror or exc}.") from None
        console.print(f"job config with this layout written to {config_out}; pass it as --config to calibrate, "
                      "analyze and monitor", highlight=False, soft_wrap=True)
    else:
        console.print("add to your job config (layerwatch.toml), or re-run with --config-out FILE:", highlight=False, soft_wrap=True)
        console.print(toml, highlight=False, markup=False)


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.command("markers")(markers)
