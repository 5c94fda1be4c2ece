"""Images of real jobs: each analysed layer's top view, reference and overlay, kept per job.

Layout under the image folder the dashboard and ``layerwatch report`` read
(``layerwatch serve --images``, default: the history database's folder)::

    jobs/<job id, 6 digits>/tops/layer_NNNN.png       grey top view of the photo
    jobs/<job id>/refs/layer_NNNN.png                  the reference it was compared with
    jobs/<job id>/overlays/layer_NNNN.png              heatmap overlay (paper Figs. 13, 15)
    jobs/<job id>/layers/layer_NNNN.json               the LayerResult with its heatmap
    jobs/<job id>/stack.png                            layer stack, drawn when the job ends

The same files the demo writes (:class:`~layerwatch.evaluate.results.ResultsFolder`), one
folder per job; each layer's ``LayerResult.images`` holds their paths relative to the image
folder, so the history rows reference them exactly as for the demo.

Retention: after each job (and when a job starts) the oldest jobs' folders are deleted until
at most ``max_jobs`` folders remain and they take at most ``max_mb`` megabytes together; the
folder of the running job is never deleted. The history rows stay; their pictures then show
as "not stored" / "missing".
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from layerwatch.analysis.result import LayerResult
from layerwatch.errors import ConfigError, LayerwatchError
from layerwatch.evaluate.results import ResultsFolder
from layerwatch.geometry.topview import TopView

__all__ = ["ArtifactStore", "StoringPipeline"]

log = logging.getLogger("layerwatch.monitor.artifacts")


def _size(folder: Path) -> int:
    """Bytes of the files under ``folder``."""
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


class ArtifactStore:
    """Per-job image folders under ``root`` with a retention limit.

    Parameters
    ----------
    root : str or Path
        The image folder (created).
    max_mb : float, optional
        Largest total size of the job folders, MB (10^6 bytes); ``None``: no size limit.
    max_jobs : int, optional
        Most job folders kept; ``None``: no count limit.

    Raises
    ------
    ConfigError
        A limit that is not finite and positive.
    """

    def __init__(self, root: str | Path, max_mb: float | None = None, max_jobs: int | None = None) -> None:
        if max_mb is not None and not (0 < float(max_mb) < 1e9):
            raise ConfigError(f"--keep-mb {max_mb}: give a positive number of megabytes (e.g. 2000).")
        if max_jobs is not None and not (isinstance(max_jobs, int) and max_jobs >= 1):
            raise ConfigError(f"--keep-jobs {max_jobs}: give a whole number of jobs, 1 or more.")
        self.root = Path(root)
        self.max_bytes = None if max_mb is None else int(float(max_mb) * 1e6)
        self.max_jobs = max_jobs
        (self.root / "jobs").mkdir(parents=True, exist_ok=True)

    def rel(self, job_id: int) -> str:
        """Folder of ``job_id`` relative to :attr:`root`."""
        return f"jobs/{int(job_id):06d}"

    def folder(self, job_id: int, topview: TopView) -> ResultsFolder:
        """The results folder of ``job_id`` (created)."""
        return ResultsFolder(self.root / self.rel(job_id), topview)

    def job_folders(self) -> list[tuple[int, Path]]:
        """``(job id, folder)`` of every stored job, oldest (smallest id) first."""
        out = [(int(p.name), p) for p in (self.root / "jobs").iterdir() if p.is_dir() and p.name.isdigit()]
        return sorted(out)

    def prune(self, keep: int | None = None) -> list[int]:
        """Delete the oldest jobs' folders until both limits hold; returns the deleted job ids.

        Parameters
        ----------
        keep : int, optional
            Job id never deleted (the running job).
        """
        folders = self.job_folders()
        sizes = {jid: _size(p) for jid, p in folders}
        total, count = sum(sizes.values()), len(folders)
        removed = []
        for jid, path in folders:
            over_size = self.max_bytes is not None and total > self.max_bytes
            over_count = self.max_jobs is not None and count > self.max_jobs
            if not (over_size or over_count):
                break
            if jid == keep:
                continue
            shutil.rmtree(path, ignore_errors=True)
            total -= sizes[jid]
            count -= 1
            removed.append(jid)
        if removed:
            log.info("retention: deleted the images of job(s) %s (limits: %s MB, %s jobs)", removed,
                     None if self.max_bytes is None else self.max_bytes / 1e6, self.max_jobs)
        return removed

    def finish(self, job_id: int, topview: TopView, history: Any = None) -> Path | None:
        """Draw the job's layer stack; with ``history``, the job's last layer row references it.

        Returns
        -------
        Path or None
            ``stack.png``, or ``None`` when the job stored no top view.
        """
        path = self.folder(job_id, topview).stack()
        if path is None or history is None:
            return path
        try:
            last = history.latest_layer(job_id)
            if last is not None:
                last.images["stack"] = f"{self.rel(job_id)}/stack.png"
                history.add_layer(job_id, last)
        except LayerwatchError as exc:
            log.warning("layer stack not recorded: %s", exc)
        return path


class StoringPipeline:
    """A layer pipeline that also stores each analysed layer's images in an :class:`ArtifactStore`.

    Wraps any object with ``process(photo, layer_index) -> LayerResult``, ``last_top``,
    ``reference(i)`` and ``topview`` (:class:`~layerwatch.pipeline.step.LayerPipeline`);
    every other attribute is the wrapped pipeline's. A failed image write is logged and
    noted in ``result.message`` ("images not stored: ..."); the analysis result is returned either way.

    Parameters
    ----------
    pipeline : LayerPipeline
    store : ArtifactStore
    job_id : int
        History id of the job (names its folder).
    """

    def __init__(self, pipeline: Any, store: ArtifactStore, job_id: int) -> None:
        self.pipeline, self.store, self.job_id = pipeline, store, int(job_id)
        self.folder = store.folder(job_id, pipeline.topview)
        #: folder the stored image paths are relative to (the monitor attaches overlays from it)
        self.image_root = store.root

    def __getattr__(self, name: str) -> Any:
        return getattr(self.pipeline, name)

    def process(self, photo: np.ndarray, layer_index: int) -> LayerResult:
        """Analyse (see the wrapped pipeline) and store the layer's top view, reference and overlay."""
        return self.store_layer(self.pipeline.process(photo, layer_index))

    def store_layer(self, res: LayerResult) -> LayerResult:
        """Store the images of the wrapped pipeline's last analysis ``res`` (its ``last_top`` and reference) and
        name them in ``res.images``; a result that is not ``ok`` is returned as it is."""
        if res.status != "ok":
            return res
        try:
            ref = self.pipeline.reference(res.layer)
            self.folder.write(res, self.pipeline.last_top, ref.footprint, ref.image)
        except (OSError, LayerwatchError, ValueError) as exc:
            log.warning("images of layer %d not stored: %s", res.layer, exc)
            res.message = f"images not stored: {exc}"
            return res
        prefix = self.store.rel(self.job_id)
        res.images = {k: f"{prefix}/{v}" for k, v in res.images.items()}
        return res
