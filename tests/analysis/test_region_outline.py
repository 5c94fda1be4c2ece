"""Region outlines in bed mm: a top-view mask drawn back from its outline is the mask; they survive the JSON record."""

from __future__ import annotations

import cv2
import numpy as np
from analysis_scenes import TOPVIEW

from layerwatch.analysis.region_outline import outline_mask, outline_mm
from layerwatch.analysis.result import LayerResult, Region


def _blobs() -> np.ndarray:
    m = np.zeros(TOPVIEW.shape, np.uint8)
    cv2.ellipse(m, (90, 120), (40, 18), 30.0, 0, 360, 1, -1)
    cv2.rectangle(m, (200, 40), (260, 70), 1, -1)
    m[5, 5] = 1  # one pixel: below the smallest kept area
    return m.astype(bool)


def test_outline_drawn_back_is_the_mask():
    mask = _blobs()
    outline = outline_mm(mask, TOPVIEW, min_area_mm2=1.0)
    assert len(outline) == 2  # the speck is left out
    back = outline_mask(outline, TOPVIEW)
    big = mask.copy()
    big[5, 5] = False
    assert (back & big).sum() / (back | big).sum() > 0.97
    # vertices are bed mm inside the observed square
    pts = np.concatenate([np.asarray(p) for p in outline])
    x0, y0 = TOPVIEW.to_mm(np.array([0.0, TOPVIEW.shape[0] - 1]))
    x1, y1 = TOPVIEW.to_mm(np.array([TOPVIEW.shape[1] - 1, 0.0]))
    assert (pts[:, 0] >= x0 - 1e-6).all() and (pts[:, 0] <= x1 + 1e-6).all()
    assert (pts[:, 1] >= y0 - 1e-6).all() and (pts[:, 1] <= y1 + 1e-6).all()


def test_a_ring_keeps_its_hole():
    """The two bands of a diagonally shifted layer meet at its corners: the part they enclose is not marked."""
    ring = np.zeros(TOPVIEW.shape, np.uint8)
    cv2.rectangle(ring, (60, 60), (200, 180), 1, -1)
    ring[80:160, 80:180] = 0
    back = outline_mask(outline_mm(ring.astype(bool), TOPVIEW), TOPVIEW)
    assert (back == ring.astype(bool)).all()


def test_an_empty_mask_or_outline_is_nothing():
    assert outline_mm(np.zeros(TOPVIEW.shape, bool), TOPVIEW) == ()
    assert not outline_mask((), TOPVIEW).any()
    assert not outline_mask(((),), TOPVIEW).any()


def test_a_regions_outline_survives_the_json_record():
    outline = outline_mm(_blobs(), TOPVIEW)
    r = Region(area_mm2=4.0, bbox_mm=(100.0, 90.0, 110.0, 100.0), centroid_mm=(105.0, 95.0), n_blocks=2,
               mean_similarity=0.2, kind="layer_shift", kind_confidence=0.8, displacement_mm=(1.0, 0.5),
               outline_mm=outline)
    back = LayerResult.from_json(LayerResult(layer=1, z=0.4, regions=[r]).to_json()).regions[0]
    assert back.outline_mm == outline
    # a record written before outlines existed reads back without one
    old = LayerResult(layer=1, z=0.4, regions=[Region(4.0, (0.0, 0.0, 1.0, 1.0), (0.5, 0.5), 1, 0.2)]).to_dict()
    del old["regions"][0]["outline_mm"]
    assert LayerResult.from_dict(old).regions[0].outline_mm == ()
