"""Small synthetic top views for the analysis tests (no simulator needed)."""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.geometry.topview import TopView

TOPVIEW = TopView(px_per_mm=6.67, width_mm=45.0, height_mm=45.0, center_mm=(110.0, 100.0))


def part_scene(seed: int = 0, defect: str | None = None, topview: TopView = TOPVIEW):
    """Reference, photo, footprint of a hatched 20 x 16 mm rectangle centred on the view.

    ``defect``: None, "blob" (foreign blob on the part at bed (104, 103)),
    "spaghetti" (curly strands beside the part, right side), "missing" (a strip
    of the part not printed).
    """
    rng = np.random.default_rng(seed)
    h, w = topview.shape
    (u0, v1), (u1, v0) = topview.to_px(np.array([[100.0, 92.0], [120.0, 108.0]])).round().astype(int)
    foot = np.zeros((h, w), bool)
    foot[v0:v1, u0:u1] = True
    ref = np.full((h, w), 60, np.uint8)  # dark bed
    ref[foot] = 170
    for k in range(u0 - (v1 - v0), u1, 9):  # 45-degree infill lines, 9 px pitch
        cv2.line(ref, (k, v1), (k + (v1 - v0), v0), 210, 2)
    ref[~foot] = 60
    cv2.rectangle(ref, (u0, v0), (u1 - 1, v1 - 1), 230, 2)  # perimeter
    photo = cv2.GaussianBlur(ref, (3, 3), 0.8).astype(np.float32) + rng.normal(0, 1.5, (h, w))
    if defect == "blob":
        x, y = topview.to_px(np.array([104.0, 103.0])).round().astype(int)
        cv2.circle(photo, (x, y), 14, 120, -1)
        cv2.circle(photo, (x + 4, y - 3), 5, 250, -1)
    elif defect == "spaghetti":
        pts = topview.to_px(np.array([[125.0 + 3 * np.cos(t), 100 + 6 * np.sin(1.7 * t)] for t in np.linspace(0, 12, 200)]))
        cv2.polylines(photo, [pts.round().astype(np.int32)], False, 230, 2)
    elif defect == "missing":
        photo[v0 + 20 : v0 + 45, u0:u1] = 60 + rng.normal(0, 1.5, (25, u1 - u0))
    return ref, np.clip(photo, 0, 255).astype(np.uint8), foot
