"""The shared worker pool of a farm and each printer's bounded lane of pending frames.

Two pieces give back-pressure without unbounded queues:

* :class:`FrameLane` (one per printer) stands in for the monitor's analysis
  executor: it holds at most ``capacity`` pending frames and runs them, in
  layer order, on the printer's own thread. When a frame arrives and the lane
  is full, the **oldest** pending frame is dropped and ``on_drop`` records it.
  Everything that may block on the printer's side (the pause request to its
  host, history writes, alerts) runs on that thread, so a slow host never
  holds a shared worker.
* :class:`WorkerPool` (one per farm) runs the per-layer compute (reference
  rendering + warp + analysis) for every printer: on ``workers`` local threads,
  or as tasks on a Dask cluster (:mod:`layerwatch.farm.remote`). A printer's
  lane thread waits for its own layer, so the pool's queue never holds more
  than one frame per printer.

When the pool is saturated, the lanes fill up and drop their oldest frames:
a saturated farm analyses the newest layer of each printer instead of
falling further and further behind.
"""

from __future__ import annotations

import logging
import threading
import zlib
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import Any

from layerwatch.errors import ConfigError, require

__all__ = ["FrameLane", "WorkerPool"]

log = logging.getLogger("layerwatch.farm")


class FrameLane(Executor):
    """A single-thread executor with a bounded queue that drops its oldest entry when full.

    It has the two methods of :class:`concurrent.futures.Executor` a
    :class:`~layerwatch.monitor.service.Monitor` uses (``submit``, ``shutdown``).

    Parameters
    ----------
    capacity : int
        Pending calls kept (the running one not counted), >= 1.
    on_drop : callable, optional
        ``on_drop(args)`` with the positional arguments of a dropped call, from
        the thread that submitted the newer one.
    name : str
        Thread name.
    """

    def __init__(self, capacity: int = 2, on_drop: Callable[[tuple], None] | None = None,
                 name: str = "layerwatch-lane") -> None:
        if capacity < 1:
            raise ConfigError(f"a frame lane holds at least 1 frame, not {capacity}.")
        self.capacity = int(capacity)
        self.on_drop = on_drop
        self.dropped = 0
        self._pending: deque[tuple[Future, Callable, tuple, dict[str, Any]]] = deque()
        self._cv = threading.Condition()
        self._closed = False
        self._busy = False
        self._thread = threading.Thread(target=self._work, name=name, daemon=True)
        self._thread.start()

    def submit(self, fn: Callable, /, *args: Any, **kwargs: Any) -> Future:
        """Queue ``fn(*args, **kwargs)``; drop (and report) the oldest pending call when the lane is full.

        Raises
        ------
        RuntimeError
            After :meth:`shutdown` (as an executor does).
        """
        fut: Future = Future()
        dropped = None
        with self._cv:
            if self._closed:
                raise RuntimeError("cannot schedule new frames after shutdown")
            if len(self._pending) >= self.capacity:
                dropped = self._pending.popleft()
                self.dropped += 1
            self._pending.append((fut, fn, args, kwargs))
            self._cv.notify()
        if dropped is not None:
            dropped[0].cancel()
            if self.on_drop is not None:
                try:
                    self.on_drop(dropped[2])
                except Exception:  # noqa: BLE001 - recording a drop must not lose the new frame
                    log.exception("recording a dropped frame failed")
        return fut

    @property
    def pending(self) -> int:
        """Calls waiting (not running)."""
        with self._cv:
            return len(self._pending)

    def _work(self) -> None:
        while True:
            with self._cv:
                while not self._pending and not self._closed:
                    self._cv.wait()
                if not self._pending:
                    return
                fut, fn, args, kwargs = self._pending.popleft()
                self._busy = True
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn(*args, **kwargs))
                except BaseException as exc:  # noqa: BLE001 - delivered to the future's owner
                    fut.set_exception(exc)
            with self._cv:
                self._busy = False
                self._cv.notify_all()

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Accept no more frames; with ``cancel_futures``, cancel the pending ones; with ``wait``, block until
        those left ran."""
        with self._cv:
            self._closed = True
            if cancel_futures:
                while self._pending:
                    self._pending.popleft()[0].cancel()
            self._cv.notify_all()
        if wait and self._thread is not threading.current_thread():
            self._thread.join()


class WorkerPool:
    """Run the per-layer compute of every printer on shared workers.

    Parameters
    ----------
    workers : int
        Local threads (default mode), or tasks allowed in flight on the cluster.
    scheduler : str, optional
        Dask scheduler address (``"tcp://host:8786"``), or ``"local"`` for a
        :class:`distributed.LocalCluster` of worker processes started here; needs
        the ``dask`` extra. ``None``: local threads.
    client : distributed.Client, optional
        An existing client to use instead of ``scheduler`` (not closed by :meth:`close`).
    """

    def __init__(self, workers: int = 2, scheduler: str | None = None, client: Any = None) -> None:
        self.workers = max(1, int(workers))
        self.scheduler = scheduler
        self._own_client = False
        self._client = client
        self._slots = threading.BoundedSemaphore(self.workers)
        self._threads: ThreadPoolExecutor | None = None
        self._pinned: dict[str, str] = {}  # job key -> Dask worker address
        self._pin_lock = threading.Lock()
        if client is None and scheduler is not None:
            distributed = require("distributed", "dask", "a farm on a Dask cluster")
            if scheduler == "local":
                self._client = distributed.Client(distributed.LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True))
            else:
                self._client = distributed.Client(scheduler)
            self._own_client = True
        if self._client is None:
            self._threads = ThreadPoolExecutor(self.workers, thread_name_prefix="layerwatch-worker")

    @property
    def client(self) -> Any:
        """The Dask client, or ``None`` with local threads."""
        return self._client

    @property
    def distributed(self) -> bool:
        """Work goes to a Dask cluster."""
        return self._client is not None

    def scatter(self, value: Any) -> Any:
        """``value`` sent once to every Dask worker (a future standing for it); itself with local threads."""
        if self._client is None:
            return value
        return self._client.scatter(value, broadcast=True, hash=False)

    def run(self, fn: Callable, *args: Any, key: str | None = None) -> Any:
        """``fn(*args)`` on a worker; blocks the calling (printer lane) thread until it returns.

        ``key`` (a job's :attr:`JobContext.key`) pins the work to one Dask worker, the same for
        every frame of that job: its pipeline keeps per-job state between layers (the scene
        channel's expected appearance, the renderer's layer stack), so a job's frames must not
        be spread over workers. A job whose worker left is moved to another (its state restarts).

        Raises
        ------
        Exception
            Whatever ``fn`` raised (re-raised here), or the cluster's error.
        """
        if self._threads is not None:
            return self._threads.submit(fn, *args).result()
        with self._slots:  # at most `workers` frames in flight on the cluster
            if key is None:
                return self._client.submit(fn, *args, pure=False).result()
            return self._client.submit(fn, *args, pure=False, workers=[self._worker_for(key)],
                                       allow_other_workers=False).result()

    def _worker_for(self, key: str) -> str:
        """The Dask worker address that runs every frame of job ``key`` (stable while it lives)."""
        alive = sorted(self._client.scheduler_info()["workers"])
        if not alive:
            raise RuntimeError("the Dask cluster has no worker")
        with self._pin_lock:
            pinned = self._pinned.get(key)
            if pinned is not None and pinned in alive:
                return pinned
            worker: str = alive[zlib.crc32(key.encode()) % len(alive)]
            self._pinned[key] = worker
            return worker

    def close(self) -> None:
        """Stop the local threads or the client (and its cluster) this pool started."""
        if self._threads is not None:
            self._threads.shutdown(wait=True)
        if self._own_client and self._client is not None:
            cluster = getattr(self._client, "cluster", None)
            self._client.close()
            if cluster is not None:
                cluster.close()
