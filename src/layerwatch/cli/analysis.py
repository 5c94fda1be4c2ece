"""CLI verbs for the analysis stage: ``layerwatch compare``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import cv2
import numpy as np
import typer
from rich.table import Table

from layerwatch.analysis.overlay import write_overlay
from layerwatch.analysis.scene_change import changed_beside
from layerwatch.analysis.scoring import analyze_layer, grey_u8
from layerwatch.cli import console
from layerwatch.cli.params import WRITE_FILE, Finite
from layerwatch.cli.pipeline import PAPER_HELP
from layerwatch.errors import AnalysisError
from layerwatch.geometry.topview import TopView
from layerwatch.pipeline.config import resolve_config

__all__ = ["register"]


def _read_image(path: Path, what: str, mask: bool = False):
    """The image at ``path``, grey as the per-layer step reads a top view; ``mask``: non-zero pixels, bool."""
    if not path.is_file():
        raise AnalysisError(f"{what} {path} does not exist; pass an image file (PNG/JPEG).")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise AnalysisError(f"{what} {path} is not a readable image; pass a PNG or JPEG file.")
    if mask:
        return (img.reshape(img.shape[0], img.shape[1], -1) > 0).any(axis=2)
    return np.ascontiguousarray(grey_u8(img, what))


def _flags(**options) -> dict[str, dict]:
    """The options the user gave, as the ``flag`` layer of the settings (``section.key`` -> value)."""
    out: dict[str, dict] = {}
    for name, value in options.items():
        if value is not None:
            section, key = name.split("__")
            out.setdefault(section, {})[key] = value
    return out


def compare(
    photo_top: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="Photo already warped to the top view (PNG/JPEG).")],
    reference: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="Reference image of the same top view (rendered layer).")],
    mask: Annotated[Path | None, typer.Option("--mask", "-m", exists=True, dir_okay=False, help="Footprint mask image (non-zero = printed); default: whole image.")] = None,
    config: Annotated[Path | None, typer.Option("--config", "-c", exists=True, dir_okay=False, help="Job config TOML ([analysis], [topview]).")] = None,
    paper: Annotated[bool, typer.Option("--paper-settings", help=PAPER_HELP)] = False,
    metric: Annotated[str | None, typer.Option("--metric", help="Similarity measure (cosine, jaccard, pearson, ...); default: the settings'.")] = None,
    threshold: Annotated[float | None, typer.Option("--threshold", "-t", parser=Finite(0, 1), help="Block threshold T_S in [0, 1].")] = None,
    px_per_mm: Annotated[float | None, typer.Option("--px-per-mm", parser=Finite(0, 100, lo_open=True, unit="px/mm"), help="Top-view scale, pixels per millimetre.")] = None,
    cell_px: Annotated[int | None, typer.Option("--cell-px", parser=Finite(2, 64, integer=True, unit="px"), help="HOG cell size in pixels.")] = None,
    margin_mm: Annotated[float | None, typer.Option("--margin-mm", parser=Finite(0, 100, unit="mm"), help="Margin around the footprint that also counts, mm.")] = None,
    presmooth_px: Annotated[float | None, typer.Option("--presmooth-px", parser=Finite(0, 5, unit="px"), help="Gaussian pre-filter sigma of both images, px (0 = none).")] = None,
    flat_tolerance: Annotated[float | None, typer.Option("--flat-tolerance", parser=Finite(1, 10), help="Featureless tolerance of the reference's blocks (>= 1).")] = None,
    grow_threshold: Annotated[float | None, typer.Option("--grow-threshold", parser=Finite(0, 1), help="Hysteresis of the drawn failing area above T_S.")] = None,
    grow_margin_mm: Annotated[float | None, typer.Option("--grow-margin-mm", parser=Finite(0, 100, unit="mm"), help="How far beside the footprint a drawn region may grow, mm.")] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", parser=WRITE_FILE, help="Overlay PNG to write (default: <photo>_overlay.png).")] = None,
    all_metrics: Annotated[bool, typer.Option("--all-metrics", help="Also print a% for all twelve measures.")] = False,
    json_out: Annotated[Path | None, typer.Option("--json", parser=WRITE_FILE, help="Also write the LayerResult as JSON here.")] = None,
    bed_photo: Annotated[Path | None, typer.Option("--bed-photo", dir_okay=False, help="Top view of the empty bed "
                                                   "(`layerwatch warp bed.jpg`): also report what changed beside the footprint.")] = None,
) -> None:
    """Compare a top-view photo with its reference: print a% and failing regions, write the overlay.

    Settings come from the same resolver as ``analyze`` (defaults, the recommended settings unless
    ``--paper-settings``, ``-c job.toml``, then these options), so a pair ``analyze`` wrote reports the same a%.
    """
    cfg = resolve_config(config, recommended=not paper, flags=_flags(
        analysis__metric=metric, analysis__threshold=threshold, analysis__cell_px=cell_px,
        analysis__footprint_margin_mm=margin_mm, analysis__presmooth_px=presmooth_px,
        analysis__flat_tolerance=flat_tolerance, analysis__grow_threshold=grow_threshold,
        analysis__grow_margin_mm=grow_margin_mm, topview__px_per_mm=px_per_mm)).config
    top = _read_image(photo_top, "photo")
    ref = _read_image(reference, "reference")
    if top.shape != ref.shape:
        raise AnalysisError(f"photo is {top.shape[1]}x{top.shape[0]} px but the reference is {ref.shape[1]}x{ref.shape[0]}; warp/render both for the same top view.")
    foot = _read_image(mask, "mask", mask=True) if mask is not None else np.ones(top.shape, dtype=bool)
    h, w = top.shape
    ppm = cfg.topview.px_per_mm
    topview = TopView(px_per_mm=ppm, width_mm=w / ppm, height_mm=h / ppm, center_mm=cfg.topview.center_mm)
    if topview.shape != (h, w):  # pragma: no cover - rounding guard
        raise AnalysisError(f"cannot build a {w}x{h} px top view at {ppm} px/mm; adjust --px-per-mm.")
    res = analyze_layer(top, ref, foot, topview, cfg.analysis, all_metrics=all_metrics)
    _beside(res, photo_top, bed_photo, foot, topview, cfg)
    out = output or photo_top.with_name(photo_top.stem + "_overlay.png")
    write_overlay(out, top, res, topview, foot if mask is not None else None)
    res.images["overlay"] = str(out)
    _print_result(res, mask is not None)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(res.to_json(indent=1))

    console.print(f"overlay written to {out}  ({res.timings_ms['total']:.0f} ms)")


def _beside(res, photo_top: Path, bed_photo: Path | None, foot, topview, cfg) -> None:
    """``--bed-photo``: the single-photo scene check beside the footprint into ``res`` (or say it is missing)."""
    if bed_photo is None:
        console.print("[dim]no --bed-photo: what lies beside the footprint is not compared with the empty bed[/]")
        return
    if not bed_photo.is_file():
        raise AnalysisError(f"bed photo {bed_photo} does not exist; pass the empty bed's top view (layerwatch warp).")
    top = cv2.imread(str(photo_top), cv2.IMREAD_COLOR)
    bed = cv2.imread(str(bed_photo), cv2.IMREAD_COLOR)
    if top is None:
        raise AnalysisError(f"photo {photo_top} is not a readable image; pass a PNG or JPEG top view (layerwatch warp).")
    if bed is None:
        raise AnalysisError(f"bed photo {bed_photo} is not a readable image; pass a PNG or JPEG file.")
    if bed.shape != top.shape:
        raise AnalysisError(f"bed photo is {bed.shape[1]}x{bed.shape[0]} px but the photo is {top.shape[1]}x{top.shape[0]}; "
                            "warp both to the same top view.")
    res.outside_regions = changed_beside(top, bed, foot, topview, cfg.scene)
    res.outside_anomalous_mm2 = float(sum(r.area_mm2 for r in res.outside_regions))
    console.print(f"beside the footprint: {res.outside_anomalous_mm2:.1f} mm² changed against the empty bed "
                  f"in {len(res.outside_regions)} region(s)")


def _print_result(res, has_mask: bool) -> None:
    """a%, the failing regions and (when scored) all twelve measures, as tables."""
    console.print(
        f"[bold]a% = {100 * res.anomaly_ratio:.1f}%[/]  ({res.metric} < {res.threshold:.2f}; "
        f"{res.n_anomalous}/{res.n_blocks} blocks; S_A = {res.anomalous_area_mm2:.1f} mm², "
        f"S_P = {res.printed_area_mm2:.1f} mm², outside footprint {res.outside_area_mm2:.1f} mm²)"
    )
    if not has_mask:
        console.print("[dim]no --mask given: the whole image counts as printed area[/]")
    if res.regions:
        table = Table(title="failing regions (bed mm, centre from [topview]; +y up)")
        for col in ("#", "area mm²", "centroid x, y", "bbox x0, y0, x1, y1", "blocks", "mean s", "min s", "outside"):
            table.add_column(col, justify="right")
        for k, r in enumerate(res.regions[:20], start=1):
            table.add_row(
                str(k), f"{r.area_mm2:.1f}", f"{r.centroid_mm[0]:.1f}, {r.centroid_mm[1]:.1f}",
                ", ".join(f"{v:.1f}" for v in r.bbox_mm), str(r.n_blocks),
                f"{r.mean_similarity:.2f}", f"{r.min_similarity:.2f}", f"{100 * r.outside_fraction:.0f}%",
            )
        console.print(table)
        if len(res.regions) > 20:
            console.print(f"[dim]... and {len(res.regions) - 20} smaller regions[/]")
    else:
        console.print("no failing regions")
    if res.per_metric:
        table = Table(title=f"all measures at T_S = {res.threshold:.2f}")
        for col in ("measure", "a%", "anomalous blocks", "mean similarity"):
            table.add_column(col, justify="right")
        for name, v in res.per_metric.items():
            table.add_row(name, f"{100 * v.anomaly_ratio:.1f}", str(v.n_anomalous), f"{v.mean_similarity:.3f}")
        console.print(table)


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.command("compare")(compare)
