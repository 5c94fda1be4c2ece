"""CLI verbs for the analysis stage: ``layerwatch compare``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from layerwatch.cli.params import WRITE_FILE, Finite

__all__ = ["register"]


def _read_image(path: Path, what: str, grey: bool = False):
    import cv2
    import numpy as np

    from layerwatch.errors import AnalysisError

    if not path.is_file():
        raise AnalysisError(f"{what} {path} does not exist; pass an image file (PNG/JPEG).")
    flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_UNCHANGED
    img = cv2.imread(str(path), flag)
    if img is None:
        raise AnalysisError(f"{what} {path} is not a readable image; pass a PNG or JPEG file.")
    if img.ndim == 3:
        img = img[..., :3][..., ::-1]  # BGR(A) -> RGB
    return np.ascontiguousarray(img)


def compare(
    photo_top: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="Photo already warped to the top view (PNG/JPEG).")],
    reference: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="Reference image of the same top view (rendered layer).")],
    mask: Annotated[Path | None, typer.Option("--mask", "-m", exists=True, dir_okay=False, help="Footprint mask image (non-zero = printed); default: whole image.")] = None,
    metric: Annotated[str, typer.Option("--metric", help="Similarity measure (cosine, sqeuclidean, pearson, ...).")] = "cosine",
    threshold: Annotated[float, typer.Option("--threshold", "-t", parser=Finite(0, 1), help="Block threshold T_S in [0, 1].")] = 0.7,
    px_per_mm: Annotated[float, typer.Option("--px-per-mm", parser=Finite(0, 100, lo_open=True, unit="px/mm"), help="Top-view scale, pixels per millimetre.")] = 6.67,
    cell_px: Annotated[int, typer.Option("--cell-px", parser=Finite(2, 64, integer=True, unit="px"), help="HOG cell size in pixels.")] = 8,
    margin_mm: Annotated[float, typer.Option("--margin-mm", parser=Finite(0, 100, unit="mm"), help="Margin around the footprint that also counts, mm.")] = 5.0,
    output: Annotated[Path | None, typer.Option("-o", "--output", parser=WRITE_FILE, help="Overlay PNG to write (default: <photo>_overlay.png).")] = None,
    all_metrics: Annotated[bool, typer.Option("--all-metrics", help="Also print a% for all twelve measures.")] = False,
    json_out: Annotated[Path | None, typer.Option("--json", parser=WRITE_FILE, help="Also write the LayerResult as JSON here.")] = None,
) -> None:
    """Compare a top-view photo with its reference: print a% and failing regions, write the overlay."""
    import numpy as np
    from rich.table import Table

    from layerwatch.analysis.overlay import write_overlay
    from layerwatch.analysis.scoring import analyze_layer
    from layerwatch.analysis.settings import METRIC_NAMES, AnalysisSettings
    from layerwatch.cli import console
    from layerwatch.errors import AnalysisError
    from layerwatch.geometry.topview import TopView

    if metric not in METRIC_NAMES:
        raise AnalysisError(f"unknown measure {metric!r}; use one of {', '.join(METRIC_NAMES)}.")
    top = _read_image(photo_top, "photo")
    ref = _read_image(reference, "reference")
    if top.shape[:2] != ref.shape[:2]:
        raise AnalysisError(f"photo is {top.shape[1]}x{top.shape[0]} px but the reference is {ref.shape[1]}x{ref.shape[0]}; warp/render both for the same top view.")
    if mask is not None:
        foot = _read_image(mask, "mask", grey=True) > 0
    else:
        foot = np.ones(top.shape[:2], dtype=bool)
    h, w = top.shape[:2]
    topview = TopView(px_per_mm=px_per_mm, width_mm=w / px_per_mm, height_mm=h / px_per_mm)
    if topview.shape != (h, w):  # pragma: no cover - rounding guard
        raise AnalysisError(f"cannot build a {w}x{h} px top view at {px_per_mm} px/mm; adjust --px-per-mm.")
    try:
        settings = AnalysisSettings(metric=metric, threshold=threshold, cell_px=cell_px, footprint_margin_mm=margin_mm)
    except ValueError as exc:
        raise AnalysisError(f"invalid analysis option: {str(exc).splitlines()[-1].strip()}") from None
    res = analyze_layer(top, ref, foot, topview, settings, all_metrics=all_metrics)
    out = output or photo_top.with_name(photo_top.stem + "_overlay.png")
    write_overlay(out, top, res, topview, foot if mask is not None else None)
    res.images["overlay"] = str(out)

    console.print(
        f"[bold]a% = {100 * res.anomaly_ratio:.1f}%[/]  ({res.metric} < {res.threshold:.2f}; "
        f"{res.n_anomalous}/{res.n_blocks} blocks; S_A = {res.anomalous_area_mm2:.1f} mm², "
        f"S_P = {res.printed_area_mm2:.1f} mm², outside footprint {res.outside_area_mm2:.1f} mm²)"
    )
    if mask is None:
        console.print("[dim]no --mask given: the whole image counts as printed area[/]")
    if res.regions:
        table = Table(title="failing regions (image-centred mm; +y up)")
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
    if all_metrics:
        table = Table(title=f"all measures at T_S = {threshold:.2f}")
        for col in ("measure", "a%", "anomalous blocks", "mean similarity"):
            table.add_column(col, justify="right")
        for name, v in res.extra["per_metric"].items():
            table.add_row(name, f"{100 * v['anomaly_ratio']:.1f}", str(v["n_anomalous"]), f"{v['mean_similarity']:.3f}")
        console.print(table)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(res.to_json(indent=1))
    console.print(f"overlay written to {out}  ({res.timings_ms['total']:.0f} ms)")


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.command("compare")(compare)
