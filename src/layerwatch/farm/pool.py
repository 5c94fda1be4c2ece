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
  or as tasks on a Dask cluster (:mod:`layerwatch.farm.remote`: there the whole
  frame, from the camera's JPEG bytes to the lag check's analysis), each job pinned
  to the least loaded worker process, with a few frames in flight per worker
  (handed out first come, first served: :class:`FairSlots`). A
  printer's lane thread waits for its own layer, so the pool's queue never holds
  more than one frame per printer.

When the pool is saturated, the lanes fill up and drop their oldest frames:
a saturated farm analyses the newest layer of each printer instead of
falling further and further behind.

Worker processes started here (``scheduler="local"``) keep glibc's *dynamic* mmap threshold: Dask
starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536`` (``distributed.nanny.pre-spawn-environ``),
which fixes the threshold, so every large temporary of a frame (a 1080p photo is 6 MB; the analysis
makes dozens of arrays above 128 kB) is mapped and faulted in anew: measured 211 ms CPU per frame in
such a worker against 90 ms without it (:func:`dynamic_malloc`). A cluster started elsewhere
(``dask worker``) should be configured the same way (docs/farm.md).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import numpy as np

from layerwatch.errors import ConfigError, LayerwatchError, require
from layerwatch.farm.remote import forget_pipeline

__all__ = ["FairSlots", "FrameLane", "WorkerLost", "WorkerPool", "LOST_CHECK_S", "REFRESH_S", "dynamic_malloc"]

log = logging.getLogger("layerwatch.farm")

#: how often the cached list of Dask workers is refreshed, s
REFRESH_S = 10.0
#: how often a waiting frame checks that its worker is still there, s
LOST_CHECK_S = 15.0
#: arrays at least this large (bytes) go straight to their worker, not through the scheduler; 0: never
DIRECT_BYTES = 1 << 20


#: the environment variable Dask's nanny sets in its workers (module notes)
TRIM_VARIABLE = "MALLOC_TRIM_THRESHOLD_"


@contextmanager
def dynamic_malloc() -> Iterator[None]:
    """Dask worker processes spawned inside keep glibc's dynamic mmap threshold (module notes).

    Dask's ``distributed.nanny.pre-spawn-environ`` sets ``MALLOC_TRIM_THRESHOLD_`` in the spawning
    process's environment, which the workers inherit; inside this context it is unset there (and in
    Dask's config), and put back after.
    """
    import dask

    saved = os.environ.pop(TRIM_VARIABLE, None)
    try:
        with dask.config.set({f"distributed.nanny.pre-spawn-environ.{TRIM_VARIABLE}": None}):
            yield
    finally:
        os.environ.pop(TRIM_VARIABLE, None)
        if saved is not None:
            os.environ[TRIM_VARIABLE] = saved


class FairSlots:
    """A counting semaphore that hands a freed slot to the longest waiter (first come, first served).

    :class:`threading.Semaphore` lets the thread that just released a slot take it again before the
    woken waiter runs (it keeps the GIL): a printer whose verdict just came would send its next frame
    ahead of printers that waited longer, and under saturation some printers would starve. Here a
    released slot goes straight to the oldest waiter. A context manager, as a semaphore.

    Parameters
    ----------
    value : int
        Slots, >= 1.
    """

    def __init__(self, value: int) -> None:
        self._free = int(value)
        self._waiters: deque[threading.Event] = deque()
        self._lock = threading.Lock()

    def acquire(self) -> None:
        """Take a slot; waits behind every thread that asked before."""
        with self._lock:
            if self._free > 0 and not self._waiters:
                self._free -= 1
                return
            turn = threading.Event()
            self._waiters.append(turn)
        turn.wait()  # the releasing thread handed its slot over

    def release(self) -> None:
        """Free a slot: to the oldest waiter, if any."""
        with self._lock:
            if self._waiters:
                self._waiters.popleft().set()
            else:
                self._free += 1

    def __enter__(self) -> FairSlots:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


class WorkerLost(LayerwatchError):
    """The Dask worker holding a job's frame left (or the cluster has none)."""


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

    On a Dask cluster each job is *pinned* to one worker process (its pipeline keeps
    per-job state between layers, :mod:`layerwatch.farm.remote`): a new job goes to
    the worker with the fewest live jobs, so the work is balanced however the jobs'
    names hash, and :meth:`release` frees the pin (and the worker's pipeline) when the
    job ends. Each worker has its own slots: at most ``inflight`` frames per worker
    thread are on the cluster, so one busy worker never holds frames meant for an idle
    one, and the next frame is already on the worker when the previous one finishes
    (its transfer overlaps the compute); a freed slot goes to the printer that waited longest
    (:class:`FairSlots`), so no printer starves when the workers are saturated. The worker list is cached (refreshed every
    :data:`REFRESH_S` seconds or when a pinned worker is missing), so a frame costs one
    task round trip, not a scheduler query as well.

    Parameters
    ----------
    workers : int
        Local threads (default mode); with ``scheduler="local"``, the worker processes started.
    scheduler : str, optional
        Dask scheduler address (``"tcp://host:8786"``), or ``"local"`` for a
        :class:`distributed.LocalCluster` of worker processes started here; needs
        the ``dask`` extra. ``None``: local threads.
    client : distributed.Client, optional
        An existing client to use instead of ``scheduler`` (not closed by :meth:`close`).
    inflight : int
        Frames on the cluster per worker thread (one computing, the rest already sent), >= 1.
    """

    def __init__(self, workers: int = 2, scheduler: str | None = None, client: Any = None,
                 inflight: int = 2) -> None:
        if inflight < 1:
            raise ConfigError(f"a Dask worker takes at least 1 frame at a time, not {inflight}.")
        self.workers = max(1, int(workers))
        self.scheduler = scheduler
        self.inflight = int(inflight)
        self._own_client = False
        self._client = client
        self._threads: ThreadPoolExecutor | None = None
        self._pinned: dict[str, str] = {}  # live job key -> Dask worker address
        self._slots: dict[str, FairSlots] = {}  # worker address -> its frames in flight (first come, first served)
        self._alive: list[str] = []
        self._seen_at = -math.inf
        self._direct = True  # photos straight to their worker (until that fails once)
        self._lock = threading.Lock()
        if client is None and scheduler is not None:
            distributed = require("distributed", "dask", "a farm on a Dask cluster")
            if scheduler == "local":
                with dynamic_malloc():  # (module notes: 2.3x the CPU per frame otherwise)
                    self._client = distributed.Client(distributed.LocalCluster(
                        n_workers=self.workers, threads_per_worker=1, processes=True, dashboard_address=None))
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

    @property
    def jobs_per_worker(self) -> dict[str, int]:
        """Live (pinned) jobs on each known Dask worker (empty with local threads)."""
        with self._lock:
            return {w: sum(p == w for p in self._pinned.values()) for w in self._alive}

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
        WorkerLost
            The job's Dask worker left while it held the frame (the next frame goes to another).
        Exception
            Whatever ``fn`` raised (re-raised here), or the cluster's error.
        """
        if self._threads is not None:
            return self._threads.submit(fn, *args).result()
        worker = self._worker_for(key)
        with self._slot(worker):
            sent = [self._ship(a, worker) for a in args]
            fut = self._client.submit(fn, *sent, pure=False, workers=[worker], allow_other_workers=False)
            while True:  # a task pinned to a worker that left would wait for it for ever
                try:
                    return fut.result(timeout=LOST_CHECK_S)
                except TimeoutError:
                    if worker not in self._workers(refresh=True):
                        fut.cancel()
                        if key is not None:
                            self.release(key)
                        raise WorkerLost(f"Dask worker {worker} left while analysing this frame; "
                                         "the job's next frame goes to another worker") from None

    def _ship(self, arg: Any, worker: str) -> Any:
        """``arg``, or for a photo-sized array a future of it sent straight to ``worker``.

        A task's arguments travel through the scheduler (client -> scheduler -> worker); a 1080p
        photo (6 MB) sent directly takes one hop instead of two, and the scheduler, which serves
        every printer, never handles its bytes.
        """
        if not (DIRECT_BYTES and self._direct and isinstance(arg, np.ndarray) and arg.nbytes >= DIRECT_BYTES):
            return arg
        try:
            return self._client.scatter(arg, workers=[worker], direct=True, hash=False)
        except (OSError, TimeoutError) as exc:  # the workers' ports are not reachable from here: via the scheduler
            log.warning("cannot send photos straight to Dask worker %s (%s); they go through the scheduler", worker, exc)
            self._direct = False
            return arg

    def _workers(self, refresh: bool = False) -> list[str]:
        """Addresses of the cluster's workers (cached for :data:`REFRESH_S` seconds)."""
        now = time.monotonic()
        with self._lock:
            if not refresh and now - self._seen_at < REFRESH_S and self._alive:
                return self._alive
        info = self._scheduler_workers()
        with self._lock:
            self._alive, self._seen_at = sorted(info), now
            for w, d in info.items():
                if w not in self._slots:
                    self._slots[w] = FairSlots(self.inflight * max(1, int(d.get("nthreads", 1))))
            return self._alive

    def _scheduler_workers(self) -> dict[str, dict]:
        """The scheduler's workers now (address -> its info), asked of the scheduler itself.

        Not ``Client.scheduler_info()``: it stores the scheduler's answer in a field of the client
        and returns that field, which the client's own periodic refresh (every 2 s) overwrites
        with an identity *without* workers; a pool that read it in between saw an empty cluster
        (measured: a frame recorded as "the Dask cluster has no worker" on a live 2-worker cluster),
        and a job's worker that seemed gone would be moved, restarting its pipeline.
        """
        client = self._client
        return dict(client.sync(client.scheduler.identity, n_workers=-1)["workers"])

    def _slot(self, worker: str) -> FairSlots:
        with self._lock:
            return self._slots[worker]

    def _worker_for(self, key: str | None) -> str:
        """The Dask worker that runs job ``key``'s frames: its pinned one while alive, else the least loaded."""
        alive = self._workers()
        with self._lock:
            pinned = self._pinned.get(key) if key is not None else None
        if pinned is not None and pinned not in alive:
            alive = self._workers(refresh=True)
        if not alive:
            raise WorkerLost("the Dask cluster has no worker; start `dask worker tcp://SCHEDULER:8786` on a machine")
        with self._lock:
            if pinned is not None and pinned in alive:
                return pinned
            load = {w: 0 for w in alive}
            for w in self._pinned.values():
                if w in load:
                    load[w] += 1
            worker = min(alive, key=lambda w: (load[w], w))
            if key is not None:
                self._pinned[key] = worker
            return worker

    def release(self, key: str) -> None:
        """Job ``key`` ended: free its worker pin and drop its pipeline there (no-op with local threads)."""
        with self._lock:
            worker = self._pinned.pop(key, None)
        if worker is None or self._client is None:
            return
        try:  # fire and forget: a worker that left took the pipeline with it
            self._client.submit(forget_pipeline, key, pure=False, workers=[worker], allow_other_workers=False)
        except Exception:  # noqa: BLE001 - the client is closing; nothing to free
            log.debug("could not drop the pipeline of %s on %s", key, worker, exc_info=True)

    def close(self) -> None:
        """Stop the local threads or the client (and its cluster) this pool started."""
        if self._threads is not None:
            self._threads.shutdown(wait=True)
        if self._own_client and self._client is not None:
            cluster = getattr(self._client, "cluster", None)
            self._client.close()
            if cluster is not None:
                cluster.close()
