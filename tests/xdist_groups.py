"""How tests share the pytest-xdist workers: ``xdist_group`` under pytest 9.2, and ``exclusive`` tests.

**Groups.** ``--dist loadgroup`` groups by ``xdist_group`` again under pytest 9.2 (pytest-xdist issue 1386).

pytest-xdist 3.8 tells its controller which group a test is in by appending ``@<group>`` to the node id
each worker reports, written to ``item._nodeid``. pytest 9.2 derives ``item.nodeid`` from a structured id
(``item._id``), so that write is lost: nothing fails, but every grouped test is scheduled on its own and
the real-server tests of group ``"servers"`` ran on both workers at once. On each worker, after xdist's
own hook, this writes the suffix where pytest 9.2 reads it; where xdist's write took effect (an older
pytest, a fixed xdist) it does nothing. Loaded by ``tests/conftest.py``; ``tests/test_xdist_groups.py``
checks that a group stays on one worker.

**Exclusive tests.** A test marked ``exclusive`` runs while no test runs on any other worker: the other
worker finishes its current test and waits. For tests whose simulated printers keep wall-clock time
(layers every 0.5-2 s) and must analyse most layers as they come: on the 2-core CI machine they need the
cores a serial run gave them (beside a busy worker, a 20-printer farm dropped the failing printer's late
frames and it finished unpaused). A readers-writer lock of two ``flock`` files in the run's shared
temporary folder, writer first: every test holds the lock shared, an exclusive one holds it alone.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator

import pytest


def group_suffix(item: pytest.Item) -> str:
    """``"@a_b"`` for a test in xdist groups ``a`` and ``b`` (xdist's format), ``""`` for none."""
    names = {str(m.args[0] if m.args else m.kwargs.get("name", "default")) for m in item.iter_markers("xdist_group")}
    return "@" + "_".join(sorted(names)) if names else ""


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    # pytest >= 9.2 derives node ids from the structured ``_id``
    try:
        from _pytest.nodeid import coerce_node_id
    except ImportError:  # an older pytest reads ``_nodeid``, which xdist writes itself: nothing to mend
        return

    # xdist schedules by node id: items sharing one run once. schemathesis' items (one per API operation)
    # all have their function's id under pytest 9.2 ("test_no_server_errors", 19 times): name them in full
    seen: dict[str, int] = {}
    for item in items:
        seen[item.nodeid] = seen.get(item.nodeid, 0) + 1
    for item in items:
        if seen[item.nodeid] > 1 and item.parent is not None and hasattr(item, "_id"):
            item._id = coerce_node_id(f"{item.parent.nodeid}::{item.name}")
    same = len(items) - len({item.nodeid for item in items})
    if same:
        raise pytest.UsageError(f"xdist_groups: {same} tests share a node id; xdist would run them once")
    if not getattr(config.option, "loadgroup", False):  # set by xdist on a worker of --dist loadgroup
        return
    for item in items:
        suffix = group_suffix(item)
        if not suffix or item.nodeid.endswith(suffix):
            continue
        if not hasattr(item, "_id"):  # pytest < 9.2 reads _nodeid, which xdist wrote: cannot get here
            raise pytest.UsageError(f"xdist_groups: cannot mark {item.nodeid} as in group {suffix[1:]}")
        item._id = coerce_node_id(item.nodeid + suffix)


@pytest.fixture(autouse=True)
def _exclusive_across_workers(request: pytest.FixtureRequest,
                              tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Hold the workers' lock around each test: alone for ``exclusive`` tests, shared for the rest."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        yield
        return
    root = tmp_path_factory.getbasetemp().parent  # the run's folder, above each worker's popen-gwN
    alone = request.node.get_closest_marker("exclusive") is not None
    with open(root / "exclusive.turnstile", "a") as turnstile, open(root / "exclusive.lock", "a") as lock:
        if alone:
            fcntl.flock(turnstile, fcntl.LOCK_EX)  # no test starts on another worker from now on
            fcntl.flock(lock, fcntl.LOCK_EX)  # and the running ones have finished
        else:
            fcntl.flock(turnstile, fcntl.LOCK_SH)  # waits while an exclusive test waits or runs
            fcntl.flock(lock, fcntl.LOCK_SH)
            fcntl.flock(turnstile, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
            if alone:
                fcntl.flock(turnstile, fcntl.LOCK_UN)
