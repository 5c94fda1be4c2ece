"""One scenario of the cross-part evaluation's plan, set up as the report runs it (tests' helper)."""

from __future__ import annotations

from pathlib import Path

import pytest


def report_case(gcode: Path, scenario: str, layers: int = 200, seed: int = 0, beside_share: float = 0.3):
    """Scenario ``scenario`` of ``layerwatch evaluate --gcode GCODE --layers N --seed S --beside-share B``.

    Returns ``(sim, pipe, layers)``: its :class:`PrintSimulator` (simulator seed: the scenario's index in the
    plan, as the report's), a fresh :class:`LayerPipeline` on a 1280 x 720 camera with the job settings that
    ``evaluate --gcode`` derives, a new print started on the simulated bed photo, and the scenario's photographed
    layers. Skips when the file is not in the shared data.
    """
    from layerwatch.cli.pipeline import job_settings
    from layerwatch.evaluate.harness import plan_frames
    from layerwatch.gcode import read_toolpath
    from layerwatch.pipeline.step import LayerPipeline
    from layerwatch.simulate import PrintSimulator, default_camera

    if not gcode.is_file():
        pytest.skip(f"{gcode.name} not in the shared data")
    tp = read_toolpath(gcode)
    cfg = job_settings(None, gcode, tp).config
    cam = default_camera(cfg.topview.topview(), image_size=(1280, 720))
    cfg = cfg.for_camera(cam)
    plan = plan_frames(tp, layers, seed=seed, beside_share=beside_share)
    k = next(i for i, (s, _) in enumerate(plan) if s.name == scenario)
    scen, photographed = plan[k]
    sim = PrintSimulator(tp, cam, cfg.topview.topview(), scen, seed=k)
    pipe = LayerPipeline(tp, cam, cfg, memo=tp.n_layers)
    pipe.new_print(sim.bed_photo())
    return sim, pipe, photographed
