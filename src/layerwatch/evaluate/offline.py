"""Offline analysis of a series of layer photos (``layerwatch analyze``).

Photos are matched to layers by the last number in their file name
(``layer_0012.png``, ``img-12.jpg``; 0-based layer index) or, when no name
has a number, by their order. Missing layers, duplicates and unreadable or
unwarpable photos are reported per layer; the run goes on and results
already in the output folder are kept and not recomputed (resumable).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from layerwatch.analysis.result import LayerResult
from layerwatch.errors import ConfigError
from layerwatch.evaluate.results import ResultsFolder
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.pipeline.config import JobConfig
from layerwatch.pipeline.policy import first_stop
from layerwatch.pipeline.step import LayerPipeline

__all__ = ["OfflineRun", "assign_layers", "run_offline"]

_NUM = re.compile(r"(\d+)")
_TRUTH_SUFFIXES = ("_truth", "_area")  # simulator ground-truth masks written beside the photos
_BED_STEMS = ("bed",)  # the empty-bed photo (`simulate` writes bed.png, `calibrate` <model>_bed.*)


def assign_layers(photos: Sequence[str | Path], n_layers: int) -> tuple[dict[int, Path], list[str]]:
    """Map layer index -> photo path; returns the map and problems (duplicates, out of range)."""
    paths = [Path(p) for p in photos]
    truth = [p for p in paths if p.stem.endswith(_TRUTH_SUFFIXES)]
    beds = [p for p in paths if p.stem == "bed" or p.stem.endswith("_bed")]
    paths = [p for p in paths if not p.stem.endswith(_TRUTH_SUFFIXES) and p not in beds]
    nums = [_NUM.findall(p.stem) for p in paths]
    problems: list[str] = []
    if truth:
        problems.append(f"{len(truth)} ground-truth mask file(s) (*_truth/*_area, from `layerwatch simulate`) "
                        "are not photos; skipped")
    if beds:
        problems.append(f"{', '.join(p.name for p in beds)}: the empty-bed photo is not a layer photo; skipped "
                        "(it is the scene's baseline: --bed-photo, or recorded with the camera)")
    out: dict[int, Path] = {}
    if paths and all(nums):
        for p, ns in zip(paths, nums, strict=True):
            i = int(ns[-1])
            if not 0 <= i < n_layers:
                problems.append(f"{p.name}: layer {i} is not in the G-code (0..{n_layers - 1}); skipped")
            elif i in out:
                problems.append(f"{p.name}: layer {i} already has {out[i].name}; skipped")
            else:
                out[i] = p
    else:
        for i, p in enumerate(paths):
            if i >= n_layers:
                problems.append(f"{p.name}: more photos than layers; skipped")
            else:
                out[i] = p
    return out, problems


@dataclass
class OfflineRun:
    """Outcome of :func:`run_offline`."""

    results: dict[int, LayerResult] = field(default_factory=dict)
    reused: int = 0
    missing: list[int] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    paused_at: int | None = None
    reason: str = ""


def run_offline(
    toolpath: Toolpath,
    camera: CameraModel,
    config: JobConfig,
    photos: Sequence[str | Path],
    out: str | Path,
    *,
    cache_dir: str | Path | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    bed_photo: np.ndarray | None = None,
) -> OfflineRun:
    """Analyse every photo and write the results folder (resumable).

    ``bed_photo`` is the scene channel's first expected appearance
    (:class:`~layerwatch.pipeline.scene.SceneModel`). Results reused from an
    earlier run still pass their photo to the scene model (no analysis), so
    the layers analysed after them are compared with the right scene.

    Returns
    -------
    OfflineRun
        Results by layer (reused ones included), missing layers, per-photo
        problems (scene notes included), and the first layer where the pause rule fires.
    """
    if not photos:
        raise ConfigError("no photos given; pass the layer photos (e.g. photos/*.png).")
    mapping, problems = assign_layers(photos, toolpath.n_layers)
    run = OfflineRun(problems=problems)
    pipe = LayerPipeline(toolpath, camera, config, cache_dir=cache_dir, bed_photo=bed_photo)
    folder = ResultsFolder(out, pipe.topview)
    done = folder.done()
    todo = sorted(mapping)
    last = max(todo) if todo else -1
    run.missing = [i for i in range(last + 1) if i not in mapping]
    for k, i in enumerate(todo):
        prev = done.get(i)
        if prev is not None and prev.status != "error":
            run.results[i] = prev
            run.reused += 1
            if pipe.scene is not None:  # the scene model must still see the layer (no analysis)
                photo = cv2.imread(str(mapping[i]), cv2.IMREAD_COLOR)
                if photo is not None:
                    pipe.scene.update(pipe.scene.observe(photo, i, pipe.footprint))
        else:
            path = mapping[i]
            photo = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if photo is None:
                res = LayerResult(layer=i, z=float(toolpath.layers[i].z), status="error",
                                  message=f"{path.name} is not a readable image; re-take or convert it.")
                folder.write(res)
            else:
                res = pipe.process(photo, i)
                ref = pipe.reference(i) if res.status != "error" else None
                res.images["photo"] = str(path)
                folder.write(res, pipe.last_top, None if ref is None else ref.footprint,
                             None if ref is None else ref.image)
            run.results[i] = res
            if res.status == "error":
                run.problems.append(f"layer {i} ({mapping[i].name}): {res.message}")
            elif res.message:
                run.problems.append(f"layer {i}: {res.message}")
        if progress is not None:
            progress(k + 1, len(todo), f"layer {i}")
    stop = first_stop((run.results[i] for i in sorted(run.results)), config.policy)
    if stop is not None:
        run.paused_at, run.reason = stop.layer, stop.reason
    folder.stack()
    folder.summary(run.results, run.paused_at, run.reason, extra={
        "photos": len(mapping), "missing layers": run.missing or "none", "reused": run.reused,
        "policy": "pipeline.policy.PausePolicy",
    })
    return run
