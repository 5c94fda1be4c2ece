"""Fixtures for the dashboard tests: a small history and a stand-in printer."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.analysis.result import LayerResult
from layerwatch.storage.history import History


class StandInPrinter:
    """Minimal duck-typed printer (the monitor area's VirtualPrinter may replace it)."""

    def __init__(self) -> None:
        self.state = "printing"
        self.calls: list[str] = []

    def status(self) -> dict:
        return {"state": self.state}

    def pause(self) -> None:
        self.calls.append("pause")
        self.state = "paused"

    def resume(self) -> None:
        self.calls.append("resume")
        self.state = "printing"

    def cancel(self) -> None:
        self.calls.append("cancel")
        self.state = "cancelled"


@pytest.fixture
def printer() -> StandInPrinter:
    return StandInPrinter()


@pytest.fixture
def image_root(tmp_path):
    import cv2

    root = tmp_path / "results"
    root.mkdir()
    rng = np.random.default_rng(0)
    for kind in ("top", "reference", "overlay"):
        img = rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
        cv2.imwrite(str(root / f"layer_0009_{kind}.png"), img)
    (tmp_path / "secret.txt").write_text("do not serve")
    return root


@pytest.fixture
def history(tmp_path):
    h = History(tmp_path / "history.db")
    job = h.start_job("virtual", gcode_path="part.gcode", gcode_hash="ab12", part="part")
    for i in range(10):
        ratio = 0.002 * i if i < 7 else 0.05 * (i - 6)
        h.add_layer(job, LayerResult(
            layer=i, z=0.3 * (i + 1), anomaly_ratio=ratio, metric="pearson", threshold=0.45,
            images={k: f"layer_{i:04d}_{k}.png" for k in ("top", "reference", "overlay")},
        ))
    h.add_event(job, "notify", "a% rising at layer 8")
    h.add_event(job, "pause", "a% above 10 % at layer 9", {"layer": 9})
    yield h
    h.close()
