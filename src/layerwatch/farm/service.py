"""A farm: one service running a monitor for every printer of ``farm.toml``.

:class:`Farm` owns the shared :class:`~layerwatch.farm.pool.WorkerPool`, the
simulated prints of ``camera = "sim"`` printers and one
:class:`~layerwatch.farm.station.Station` per printer, each on its own
thread. The dashboard receives :attr:`Farm.printers` (name -> station, with
``pause``/``resume``/``cancel``/``status``/``summary``), so its printer routes,
CSRF guard and audit log serve the farm unchanged.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from layerwatch.farm.config import FarmConfig
from layerwatch.farm.pool import WorkerPool
from layerwatch.farm.simcam import SimFrames
from layerwatch.farm.station import Station
from layerwatch.monitor.artifacts import ArtifactStore

__all__ = ["Farm"]

log = logging.getLogger("layerwatch.farm")


class Farm:
    """Watch every printer of a farm.

    Parameters
    ----------
    config : FarmConfig
    history : History
        Shared history database (jobs, layers, events, audit log).
    scheduler : str, optional
        Dask scheduler address overriding ``config.scheduler`` (``--scheduler``).
    workers : int, optional
        Overrides ``config.workers``.
    pool : WorkerPool, optional
        Use this pool (tests, benchmarks) instead of building one; not closed by :meth:`stop`.
    retry_s : tuple of float
        First and largest wait between a failed printer's set-up attempts, s.

    Real printers' layer images go to :attr:`store` (``[farm] images``, default beside the
    history database, which is where ``layerwatch serve`` reads them without ``--images``).
    """

    def __init__(self, config: FarmConfig, history: Any, *, scheduler: str | None = None,
                 workers: int | None = None, pool: WorkerPool | None = None,
                 retry_s: tuple[float, float] = (2.0, 60.0)) -> None:
        self.config = config
        self.history = history
        self._own_pool = pool is None
        self.pool = pool or WorkerPool(workers or config.workers, scheduler or config.scheduler)
        self.sims = SimFrames()
        self.store = self._store(config, history)
        self.stations: dict[str, Station] = {
            p.name: Station(p, self.pool, history, self.sims, queue_frames=config.queue_frames, store=self.store,
                            retry_s=retry_s)
            for p in config.printers}

    @staticmethod
    def _store(config: FarmConfig, history: Any) -> ArtifactStore | None:
        """The real printers' image store: ``[farm] images``, else beside the history database (``None``:
        no real printer, or an in-memory history without ``images``)."""
        if all(p.is_virtual for p in config.printers):
            return None
        root = config.images
        if root is None and getattr(history, "path", None) is not None:
            root = Path(history.path).resolve().parent
        return None if root is None else ArtifactStore(root, config.keep_mb, config.keep_jobs)

    @property
    def printers(self) -> dict[str, Station]:
        """The stations by printer name (what the dashboard's printer routes act on)."""
        return self.stations

    def start(self) -> Farm:
        """Start every printer's thread."""
        for s in self.stations.values():
            s.start()
        log.info("farm: %d printer(s), %s", len(self.stations),
                 f"Dask at {self.pool.scheduler}" if self.pool.distributed else f"{self.pool.workers} local worker(s)")
        return self

    def summaries(self) -> list[dict[str, Any]]:
        """Every printer's card, in file order (see :meth:`Station.summary`)."""
        return [s.summary() for s in self.stations.values()]

    def stop(self, timeout: float = 30.0) -> None:
        """Stop every monitor (each finishes the layer in hand) and the pool."""
        for s in self.stations.values():
            s.stop()
        for s in self.stations.values():
            s.join(timeout)
        if self._own_pool:
            self.pool.close()

    def __enter__(self) -> Farm:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
