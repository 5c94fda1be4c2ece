"""Shared fixtures for the dashboard tests: a seeded history with images, and a same-origin client."""

from __future__ import annotations

import pytest
from dashclient import dashboard_client
from seed_history import seed_job

from layerwatch.storage.history import History
from layerwatch.web.virtual import virtual_printer


@pytest.fixture
def seeded(tmp_path):
    h = History(tmp_path / "history.db")
    done = seed_job(h, tmp_path, n_layers=30, fail_at=20, outcome="cancelled", seed=1)
    live = seed_job(h, tmp_path, n_layers=40, fail_at=28, seed=2)
    yield h, tmp_path, {"done": done, "live": live}
    h.close()


@pytest.fixture
def printer():
    return virtual_printer()


@pytest.fixture
def make_client():
    return dashboard_client
