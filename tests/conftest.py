"""Shared fixtures: real data from ../shared/data, the bundled example, temp dirs."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest

#: --dist loadgroup under pytest 9.2 (see tests/xdist_groups.py)
pytest_plugins = ["xdist_groups"]

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("LAYERWATCH_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_gcode_files() -> list[Path]:
    """Every G-code file in ../shared/data/gcode (empty list when absent)."""
    d = SHARED_DATA / "gcode"
    return sorted(p for p in d.glob("*") if p.suffix in {".gcode", ".bgcode"}) if d.is_dir() else []


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The read-only shared data folder; skips when it is not beside the repository."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA} (clone with ../shared beside the repo)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def example_gcode() -> Path:
    from layerwatch.examples import PART_GCODE

    return PART_GCODE


@pytest.fixture(scope="session")
def example_stl() -> Path:
    from layerwatch.examples import PART_STL

    return PART_STL


@pytest.fixture(autouse=True)
def _layerwatch_logs_reach_caplog():
    """Every test starts with layerwatch's loggers enabled, propagating and not above WARNING.

    In the full suite, tests that check a warning with ``caplog`` (key files, apprise, the volume
    fall-back) saw nothing after earlier in-process runs (servers, the CLI, Dask) had changed logger
    state; alone they pass. The culprit was not found this session: this keeps tests independent.
    """
    root = logging.getLogger()
    if root.level > logging.WARNING:
        root.setLevel(logging.WARNING)
    for name, logger in list(logging.Logger.manager.loggerDict.items()):
        if name.startswith("layerwatch") and isinstance(logger, logging.Logger):
            logger.disabled = False
            logger.propagate = True
            if logger.level > logging.WARNING:
                logger.setLevel(logging.NOTSET)
    yield
