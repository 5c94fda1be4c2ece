"""The farm card's overlay thumbnail: drawn small, it still shows the failing regions and the footprint."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.farm.remote import THUMB_WIDTH, JobContext, analyse_on
from layerwatch.farm.simcam import SimPrint
from layerwatch.gcode import read_toolpath
from layerwatch.pipeline.config import resolve_config


def _share(img: np.ndarray, bgr: tuple[int, int, int]) -> float:
    return float(np.mean(np.all(np.abs(img.astype(int) - bgr) < 60, axis=2)))


@pytest.mark.slow
@pytest.mark.parametrize("cell_px", [8, 7])  # the default grid (drawn at 2 px per cell), and one drawn at full size
def test_thumbnail_shows_regions_and_footprint(cell_px):
    tp, cfg = read_toolpath(PART_GCODE), resolve_config(PART_CONFIG).config
    cfg = cfg.model_copy(update={"analysis": cfg.analysis.model_copy(update={"cell_px": cell_px})})
    sim = SimPrint(tp, cfg, "spaghetti", 4, 1, keep=10)
    pipe = JobContext("thumb", tp, sim.located, cfg).pipeline()
    for i in range(9):
        v = analyse_on(pipe, sim.frame(i), i)
    assert v.result.regions and v.thumb is not None
    assert v.thumb._png is None  # not drawn with the frame: only when asked for
    png = v.thumb.png()
    assert png is not None and v.thumb.png() is png  # drawn once
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[1] == THUMB_WIDTH
    assert _share(img, (255, 0, 255)) > 0.001  # failing regions, magenta
    if cell_px % 2 == 0:  # drawn small: the footprint's one-pixel outline is not averaged away
        assert _share(img, (255, 220, 0)) > 0.005  # footprint, cyan (BGR)
