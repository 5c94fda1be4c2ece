"""CLI verbs for the geometry stage: ``layerwatch calibrate`` and ``layerwatch warp``."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
from typing import Annotated

import cv2
import numpy as np
import typer
from rich.progress import Progress

from layerwatch.cli import console
from layerwatch.cli.params import WRITE_FILE, Finite
from layerwatch.errors import CalibrationError, WarpError
from layerwatch.geometry.calibration import (
    BoardSpec,
    approximate_intrinsics,
    calibrate_intrinsics,
    read_photo,
)
from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.pose import locate_bed
from layerwatch.geometry.synthetic import project_points
from layerwatch.geometry.warp import TopViewWarper
from layerwatch.pipeline.config import resolve_config

__all__ = ["register"]


def _board_size(text: str) -> tuple[int, int]:
    try:
        c, r = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CalibrationError(f"--board-size {text!r} is not COLSxROWS; write e.g. 9x6.") from None
    return c, r


def _draw_markers(photo, cam, topview):
    """Photo with the projected observed square (green) and markers (red circles)."""
    img = photo.copy()
    c = topview.corners_mm
    t = np.linspace(0, 1, 30)[:, None]
    edge = np.vstack([c[i] + t * (c[(i + 1) % 4] - c[i]) for i in range(4)])  # curved by distortion
    pts = project_points(cam, edge)
    thick = max(1, img.shape[1] // 640)
    cv2.polylines(img, [np.round(pts).astype(np.int32)], True, (0, 220, 0), thick, cv2.LINE_AA)
    for k, (u, v) in enumerate(project_points(cam, cam.markers_mm)):
        cv2.circle(img, (int(round(u)), int(round(v))), 6 * thick, (0, 0, 255), thick, cv2.LINE_AA)
        cv2.putText(img, str(k), (int(u) + 8 * thick, int(v) - 8 * thick), cv2.FONT_HERSHEY_SIMPLEX,
                    0.5 * thick, (0, 0, 255), thick, cv2.LINE_AA)
    return img


def calibrate(
    photos: Annotated[list[Path] | None, typer.Argument(exists=True, dir_okay=False, help="Board photos (with --board).")] = None,
    board: Annotated[bool, typer.Option("--board", help="Estimate intrinsics from the board PHOTOS.")] = False,
    board_size: Annotated[str, typer.Option("--board-size", help="Chessboard inner corners (ChArUco: squares), COLSxROWS.")] = "9x6",
    square_mm: Annotated[float, typer.Option("--square-mm", parser=Finite(0, 1000, lo_open=True, unit="mm"), help="Board square side, mm.")] = 25.0,
    charuco: Annotated[bool, typer.Option("--charuco", help="The board is a ChArUco board.")] = False,
    markers: Annotated[Path | None, typer.Option("--markers", exists=True, dir_okay=False, help="Photo of the bed with its markers: solve the camera pose.")] = None,
    camera: Annotated[Path | None, typer.Option("--camera", exists=True, dir_okay=False, help="Existing camera model to start from (intrinsics).")] = None,
    config: Annotated[Path | None, typer.Option("--config", "-c", exists=True, dir_okay=False, help="Job config (TOML) with markers and topview sections.")] = None,
    hfov: Annotated[float, typer.Option("--hfov", parser=Finite(10, 170, unit="degrees"), help="Horizontal field of view guess, degrees, when no board/camera is given.")] = 70.0,
    output: Annotated[Path, typer.Option("-o", "--output", parser=WRITE_FILE, help="Camera model to write (.toml or .json).")] = Path("camera.toml"),
) -> None:
    """Write a camera model: intrinsics from board photos and/or bed pose from a marker photo."""
    if not board and markers is None:
        raise CalibrationError("nothing to do: pass --board PHOTOS... and/or --markers BED_PHOTO.")
    model = None
    if board:
        if not photos:
            raise CalibrationError("--board needs photos of the board, e.g. `layerwatch calibrate --board photos/*.jpg`.")
        cols, rows = _board_size(board_size)
        spec = BoardSpec("charuco" if charuco else "chessboard", cols, rows, square_mm)
        with Progress(console=console, transient=True) as prog:
            task = prog.add_task("finding the board", total=len(photos))
            model = calibrate_intrinsics(photos, spec, progress=lambda d, n: prog.update(task, completed=d))
        console.print(f"intrinsics from {int(model.errors['views'])} of {len(photos)} photos: "
                      f"RMS reprojection error {model.errors['intrinsics_px']:.3f} px")
    elif camera is not None:
        model = CameraModel.load(camera)
    if markers is not None:
        photo = read_photo(markers)
        if model is None:
            model = approximate_intrinsics((photo.shape[1], photo.shape[0]), hfov)
            console.print(f"[yellow]no board or --camera: intrinsics guessed from a {hfov:g} deg field of view (approximate)[/]")
        cfg = resolve_config(config).config
        tv = cfg.topview.topview()
        model = locate_bed(model, photo, cfg.markers, tv)
        png = output.with_suffix(".png")
        cv2.imwrite(str(png), _draw_markers(photo, model.scaled_to((photo.shape[1], photo.shape[0])), tv))
        c = model.center_mm
        console.print(f"bed pose: reprojection error {model.errors['pose_px']:.2f} px, camera at "
                      f"({c[0]:.0f}, {c[1]:.0f}, {c[2]:.0f}) mm; markers drawn in {png}")
        model = _keep_bed_photo(model, markers, photo, output)
    assert model is not None  # --board or --markers (one is required above) set it
    model.save(output)
    console.print(f"camera model written to {output}")


def _keep_bed_photo(model, markers: Path, photo, output: Path):
    """Copy the empty-bed marker photo beside the camera model and record it there (the scene channel's baseline).

    Only a photo of the model's own resolution is kept (the scene channel
    compares frames pixel by pixel); otherwise the model is returned unchanged with a note.
    """
    if (photo.shape[1], photo.shape[0]) != tuple(model.image_size):
        console.print(f"[yellow]bed photo not kept:[/] it is {photo.shape[1]}x{photo.shape[0]}, the camera model "
                      f"{model.image_size[0]}x{model.image_size[1]}; take it at the monitoring resolution")
        return model
    bed = output.with_name(output.stem + "_bed" + markers.suffix.lower())
    if bed.resolve() != markers.resolve():
        shutil.copyfile(markers, bed)
    console.print(f"empty-bed photo kept as {bed} (the scene channel's baseline)")
    return dataclasses.replace(model, bed_photo=str(bed))


def warp(
    photo: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="Camera photo (PNG/JPEG).")],
    camera: Annotated[Path, typer.Option("--camera", exists=True, dir_okay=False, help="Camera model from `layerwatch calibrate`.")] = Path("camera.toml"),
    z: Annotated[float, typer.Option("--z", parser=Finite(0, 2000, unit="mm"), help="Height of the layer's top surface, mm.")] = 0.0,
    config: Annotated[Path | None, typer.Option("--config", "-c", exists=True, dir_okay=False, help="Job config (TOML) with a topview section.")] = None,
    output: Annotated[Path, typer.Option("-o", "--output", parser=WRITE_FILE, help="Top-view PNG to write.")] = Path("top.png"),
) -> None:
    """Warp a photo into the top view of the plane at height Z."""
    img = cv2.imread(str(photo), cv2.IMREAD_COLOR) if photo.is_file() else None
    if img is None:
        raise WarpError(f"cannot read the photo {photo}; pass a PNG or JPEG file.")
    cam = CameraModel.load(camera)
    tv = resolve_config(config).config.topview.topview()
    top, valid = TopViewWarper(cam, tv).warp(img, z)
    if not cv2.imwrite(str(output), top):
        raise WarpError(f"cannot write {output}; check the folder exists and the suffix is .png or .jpg.")
    console.print(f"top view {top.shape[1]}x{top.shape[0]} px at Z={z:g} mm written to {output} "
                  f"({100 * valid.mean():.0f}% of it seen by the camera)")


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.command("calibrate")(calibrate)
    app.command("warp")(warp)
