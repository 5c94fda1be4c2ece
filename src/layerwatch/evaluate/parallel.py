"""Run independent simulated prints on worker processes, results in the order given.

An evaluation is a list of prints that share nothing: each print is simulated
from its own seed and judged by a pipeline of its own, so the prints can run on
as many processes as there are cores and the records come out the same as in
one process. :func:`map_prints` is that loop: in-process for ``workers = 1``
(the default; progress per photo), else on a spawned process pool (progress
per finished print).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

__all__ = ["map_prints", "resolve_workers"]

R = TypeVar("R")


def resolve_workers(workers: int, tasks: int) -> int:
    """The processes to use: ``workers`` (0 = every core), at most one per task, at least 1."""
    n = (os.cpu_count() or 1) if workers == 0 else int(workers)
    return max(1, min(n, tasks))


def _noop() -> None:
    return None


def _call(fn: Callable[..., R], args: tuple) -> R:
    """Run one task in a worker: no progress callback crosses the process boundary."""
    return fn(*args, _noop)


def map_prints(fn: Callable[..., R], tasks: Sequence[tuple], weights: Sequence[int], workers: int = 1,
               progress: Callable[[int, int], None] | None = None) -> Iterator[R]:
    """``fn(*task, tick)`` for every task, yielded in the order of ``tasks``.

    Parameters
    ----------
    fn : callable
        A module-level function (it is pickled to the workers); its last argument is
        ``tick()``, called once per photo it judges (a no-op on a worker).
    tasks : sequence of tuple
        The arguments of each call (picklable: toolpaths, cameras, configurations).
    weights : sequence of int
        Photos per task (the progress total is their sum).
    workers : int
        Processes: 1 runs in this process, 0 uses every core.
    progress : callable, optional
        ``progress(done, total)`` in photos.

    Yields
    ------
    The result of each task, in the order of ``tasks``.
    """
    total = int(sum(weights))
    done = [0]

    def advance(n: int) -> None:
        done[0] += n
        if progress is not None:
            progress(done[0], total)

    n = resolve_workers(workers, len(tasks))
    if n == 1:
        for args in tasks:
            yield fn(*args, lambda: advance(1))
        return
    # spawn: a forked child would inherit OpenCV's and numba's thread pools mid-state
    with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures: list[Any] = [pool.submit(_call, fn, args) for args in tasks]
        for fut, w in zip(futures, weights, strict=True):
            result = fut.result()
            advance(int(w))
            yield result
