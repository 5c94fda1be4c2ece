"""Evaluation on worker processes: the same records as in one process, in the same order."""

from __future__ import annotations

import os

import pytest

from layerwatch.evaluate.harness import clean_false_alarms
from layerwatch.evaluate.parallel import map_prints, resolve_workers
from layerwatch.pipeline.config import JobConfig
from layerwatch.simulate import default_camera
from layerwatch.simulate.parts import box_part


def _square(x: int, tick) -> int:
    tick()
    return x * x


def test_resolve_workers_bounds():
    assert resolve_workers(1, 10) == 1
    assert resolve_workers(4, 2) == 2  # at most one process per task
    assert resolve_workers(3, 0) == 1
    assert resolve_workers(0, 1000) == min(os.cpu_count() or 1, 1000)


def test_map_prints_keeps_the_order_and_counts_progress():
    seen: list[tuple[int, int]] = []
    tasks = [(k,) for k in range(7)]
    got = list(map_prints(_square, tasks, [2] * 7, workers=1, progress=lambda d, n: seen.append((d, n))))
    assert got == [k * k for k in range(7)]
    assert seen[-1] == (7, 14)  # in-process: one tick per call, total from the weights
    seen.clear()
    got = list(map_prints(_square, tasks, [2] * 7, workers=2, progress=lambda d, n: seen.append((d, n))))
    assert got == [k * k for k in range(7)]
    assert seen[-1] == (14, 14)  # on workers: each finished task advances by its weight


@pytest.mark.slow
def test_clean_prints_on_two_processes_count_the_same_as_on_one():
    cfg = JobConfig(analysis={"footprint_margin_mm": 0.0})
    cam = default_camera(cfg.topview.topview(), image_size=(640, 360))
    tp = box_part(size_mm=20.0, height_mm=1.8, layer_h=0.3)
    one = clean_false_alarms(tp, cfg, cam, n_layers=18, pause_ratio=0.005, window_share=0.0, workers=1)
    two = clean_false_alarms(tp, cfg, cam, n_layers=18, pause_ratio=0.005, window_share=0.0, workers=2)
    assert one["prints"] == 3 and one["layers"] == 18
    assert one == two
