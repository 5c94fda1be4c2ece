"""Many printers in one service: ``layerwatch serve --farm farm.toml``.

:mod:`~layerwatch.farm.config` reads the farm file, :mod:`~layerwatch.farm.service`
runs a :mod:`~layerwatch.farm.station` per printer (its own thread and
:class:`~layerwatch.farm.monitor.FarmMonitor`), and :mod:`~layerwatch.farm.pool`
shares the per-layer work (the one pipeline step, :mod:`~layerwatch.farm.remote`)
between local threads or a Dask cluster with bounded per-printer queues.
Deployment: ``docs/farm.md``.
"""

from layerwatch.farm.config import FarmConfig, PrinterSpec, load_farm, parse_farm
from layerwatch.farm.pool import FrameLane, WorkerPool
from layerwatch.farm.service import Farm

__all__ = ["Farm", "FarmConfig", "FrameLane", "PrinterSpec", "WorkerPool", "load_farm", "parse_farm"]
