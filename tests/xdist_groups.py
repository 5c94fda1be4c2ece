"""``--dist loadgroup`` that groups by ``xdist_group`` again under pytest 9.2 (pytest-xdist issue 1386).

pytest-xdist 3.8 tells its controller which group a test is in by appending ``@<group>`` to the node id
each worker reports, written to ``item._nodeid``. pytest 9.2 derives ``item.nodeid`` from a structured id
(``item._id``), so that write is lost: nothing fails, but every grouped test is scheduled on its own and
the real-server tests of group ``"servers"`` ran on both workers at once. On each worker, after xdist's
own hook, this writes the suffix where pytest 9.2 reads it; where xdist's write took effect (an older
pytest, a fixed xdist) it does nothing. Loaded by ``tests/conftest.py``; ``tests/test_xdist_groups.py``
checks that a group stays on one worker.
"""

from __future__ import annotations

import pytest


def group_suffix(item: pytest.Item) -> str:
    """``"@a_b"`` for a test in xdist groups ``a`` and ``b`` (xdist's format), ``""`` for none."""
    names = {str(m.args[0] if m.args else m.kwargs.get("name", "default")) for m in item.iter_markers("xdist_group")}
    return "@" + "_".join(sorted(names)) if names else ""


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not getattr(config.option, "loadgroup", False):  # set by xdist on a worker of --dist loadgroup
        return
    for item in items:
        suffix = group_suffix(item)
        if not suffix or item.nodeid.endswith(suffix):
            continue
        if not hasattr(item, "_id"):  # pytest < 9.2 reads _nodeid, which xdist wrote: cannot get here
            raise pytest.UsageError(f"xdist_groups: cannot mark {item.nodeid} as in group {suffix[1:]}")
        from _pytest.nodeid import coerce_node_id

        item._id = coerce_node_id(item.nodeid + suffix)
