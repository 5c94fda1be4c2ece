"""Fixtures of the farm tests: the dashboard's same-origin test client (from tests/web)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "web"))

from dashclient import dashboard_client  # noqa: E402


@pytest.fixture
def make_client():
    return dashboard_client
