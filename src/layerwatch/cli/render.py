"""CLI verbs for the render stage: ``layerwatch render``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import cv2
import numpy as np
import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from layerwatch.cli import console
from layerwatch.cli.params import WRITE_DIR, Finite, scheduler_address
from layerwatch.errors import ConfigError, GcodeError, RenderError
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.config import resolve_config
from layerwatch.render.backend import render_layers
from layerwatch.render.blender import find_blender
from layerwatch.render.cache import ReferenceCache, file_hash
from layerwatch.render.mask import gcode_mask

__all__ = ["register", "parse_layers"]


def parse_layers(spec: str | None, n_layers: int) -> list[int]:
    """Layer indices from a spec: ``"7"``, ``"10:20"`` (Python slice, end excluded),
    ``"::5"``, ``"-1"`` (last), ``"1,4,9"``, ``"all"`` or ``None`` (every layer).

    Raises
    ------
    RenderError
        Unparseable spec or indices outside ``0..n_layers-1``.
    """
    if spec is None or spec.strip().lower() in {"", "all"}:
        return list(range(n_layers))
    out: list[int] = []
    for part in spec.split(","):
        part = part.strip()
        try:
            if ":" in part:
                bits = [int(b) if b.strip() else None for b in part.split(":")]
                if len(bits) > 3:
                    raise ValueError(part)
                out.extend(range(n_layers)[slice(*bits)])
            else:
                i = int(part)
                if not -n_layers <= i < n_layers:
                    raise RenderError(f"layer {i} does not exist (file has layers 0..{n_layers - 1}); pick one in range.")
                out.append(i % n_layers)
        except ValueError:
            raise RenderError(f"cannot read --layers {spec!r}; use e.g. 10:20, 5, 1,4,9 or all.") from None
    if not out:
        raise RenderError(f"--layers {spec!r} selects no layer (file has layers 0..{n_layers - 1}).")
    return sorted(set(out))


def _part_bounds(toolpath) -> tuple[float, float, float, float]:
    """Bounds of the part, mm: layers above the first (skips purge lines), else all."""
    b = np.array([la.bounds for la in toolpath.layers[1:]], dtype=float).reshape(-1, 4)
    b = b[np.isfinite(b).all(axis=1)]
    if len(b) == 0:
        return toolpath.bounds
    return (float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max()))


def _observed_square(topview, toolpath, centred: bool):
    """``topview``, or (no job file) the same square centred on the part's extrusions."""
    if not centred:
        return topview

    x0, y0, x1, y1 = _part_bounds(toolpath)
    return TopView(topview.px_per_mm, topview.width_mm, topview.height_mm, ((x0 + x1) / 2, (y0 + y1) / 2))


def render(
    file: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="G-code file (.gcode/.bgcode).")],
    layers: Annotated[str | None, typer.Option("--layers", "-l", help="Layers: 10:20 (end excluded), 5, 1,4,9, ::10 or all.")] = None,
    outdir: Annotated[Path, typer.Option("-o", "--outdir", parser=WRITE_DIR, help="Folder for the PNGs.")] = Path("references"),
    config: Annotated[Path | None, typer.Option("--config", "-c", exists=True, dir_okay=False, help="Job config TOML ([topview], [render]).")] = None,
    backend: Annotated[str | None, typer.Option("--backend", help="fast (default) or blender.")] = None,
    mask: Annotated[bool, typer.Option("--mask", help="Also write the footprint mask of each layer.")] = False,
    workers: Annotated[int, typer.Option("--workers", "-j", parser=Finite(0, 1024, integer=True), help="Worker processes (0 = all cores).")] = 1,
    scheduler: Annotated[str | None, typer.Option("--scheduler", parser=scheduler_address, help="Dask scheduler address, or 'local'.")] = None,
    cache: Annotated[Path | None, typer.Option("--cache", parser=WRITE_DIR, help="Reference cache folder (render once, reuse).")] = None,
) -> None:
    """Render reference images (top view) of G-code layers to PNGs."""
    if not file.is_file():
        raise GcodeError(f"G-code file {file} not found; check the path.")
    if backend not in (None, "fast", "blender"):
        raise ConfigError(f"unknown --backend {backend!r}; use fast or blender.")
    cfg = resolve_config(config, flags={"render": {"backend": backend}} if backend else None).config
    settings = cfg.render
    if settings.backend == "blender":
        find_blender()

    cols = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*cols, console=console, transient=True) as bar:
        t = bar.add_task("reading G-code", total=None)
        toolpath = read_toolpath(file, progress=lambda d, n: bar.update(t, completed=d, total=n))
    if toolpath.n_layers == 0:
        raise RenderError(f"{file} has no extruding moves to render; check it is sliced G-code.")
    idx = parse_layers(layers, toolpath.n_layers)
    topview = _observed_square(cfg.topview.topview(), toolpath, centred=config is None)
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RenderError(f"cannot create {outdir} ({exc}); pick another -o folder.") from None
    ref_cache = ReferenceCache(cache) if cache is not None else None
    clipped = 0
    with Progress(*cols, console=console, transient=True) as bar:
        t = bar.add_task(f"rendering {len(idx)} layers ({settings.backend})", total=len(idx))
        results = render_layers(
            toolpath, topview, settings, idx, workers=workers or None, scheduler=scheduler,
            cache=ref_cache, gcode_hash=file_hash(file) if ref_cache else None,
            progress=lambda d, n: bar.update(t, completed=d),
        )
        for r in results:
            clipped += r.clipped
            path = outdir / f"layer_{r.layer:04d}.png"
            if not cv2.imwrite(str(path), r.image):
                raise RenderError(f"cannot write {path}; check the -o folder is writable.")
            if mask:
                m = gcode_mask(toolpath, r.layer, topview, solid=True)
                cv2.imwrite(str(outdir / f"layer_{r.layer:04d}_mask.png"), m.astype("uint8") * 255)
    if clipped:
        console.print(f"[yellow]warning:[/] {clipped} segments reach outside the observed square and were clipped.")
    h, w = topview.shape
    console.print(f"wrote {len(idx)} references ({w}x{h} px, {topview.px_per_mm:g} px/mm) to {outdir}")


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.command("render")(render)
