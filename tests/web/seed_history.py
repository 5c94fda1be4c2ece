"""Realistic synthetic history for tests, screenshots and benchmarks.

A square part whose layers grow a spaghetti blob from ``fail_at``: per layer a
top-view photo, its reference and a heatmap overlay (simple NumPy drawings)
plus a layer-stack image, and a :class:`LayerResult` with plausible numbers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.pipeline.config import RECOMMENDED
from layerwatch.storage.history import History

__all__ = ["seed_job"]


def _images(layer: int, blob: float, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    import cv2

    ref = np.full((size, size), 40, np.uint8)
    s0, s1 = size // 4, 3 * size // 4
    ref[s0:s1, s0:s1] = 170
    for k in range(s0, s1, 6):  # infill lines alternating per layer
        if layer % 2:
            ref[k:k + 2, s0:s1] = 210
        else:
            ref[s0:s1, k:k + 2] = 210
    top = np.clip(ref.astype(np.int16) + rng.normal(0, 8, ref.shape), 0, 255).astype(np.uint8)
    heat = np.zeros((size, size), np.float32)
    if blob > 0:
        c = (int(0.62 * size), int(0.4 * size))
        r = max(2, int(blob * size * 0.25))
        cv2.circle(top, c, r, 90, -1)
        for _ in range(12):
            a, b = rng.integers(c[0] - r, c[0] + r + 1, 2), rng.integers(c[1] - r, c[1] + r + 1, 2)
            cv2.line(top, (int(a[0]), int(b[0])), (int(a[1]), int(b[1])), 240, 1)
        cv2.circle(heat, c, r, 1.0, -1)
    overlay = cv2.cvtColor(top, cv2.COLOR_GRAY2BGR)
    red = np.zeros_like(overlay)
    red[..., 2] = 255
    m = heat > 0
    overlay[m] = (0.55 * overlay[m] + 0.45 * red[m]).astype(np.uint8)
    cv2.rectangle(overlay, (s0, s0), (s1, s1), (80, 200, 80), 1)
    return top, ref, overlay


def seed_job(
    history: History,
    image_root: str | Path,
    n_layers: int = 40,
    fail_at: int | None = 25,
    printer: str = "virtual",
    part: str = "demo cube",
    outcome: str | None = None,
    images: bool = True,
    size: int = 160,
    seed: int = 0,
) -> int:
    """Write one job of ``n_layers`` synthetic layers (+ images under ``image_root``) and return its id."""
    import cv2

    from layerwatch.pipeline.config import JobConfig

    rng = np.random.default_rng(seed)
    root = Path(image_root)
    job = history.start_job(printer, gcode_path="part.gcode", gcode_hash=f"{seed:064x}", part=part, config=JobConfig())
    history.add_event(job, "start", f"job started on {printer}")
    paused = False
    for i in range(n_layers):
        blob = 0.0 if fail_at is None or i < fail_at else min(1.0, 0.15 + 0.06 * (i - fail_at))
        ratio = float(np.clip(0.01 + 0.01 * rng.random() + 0.5 * blob**1.5, 0, 1))
        rel: dict[str, str] = {}
        if images and (i >= n_layers - 3 or (fail_at is not None and i >= fail_at) or i % 10 == 0):
            top, ref, ov = _images(i, blob, size, rng)
            d = root / f"job{job}" / f"layer{i:04d}"
            d.mkdir(parents=True, exist_ok=True)
            for name, im in (("top", top), ("reference", ref), ("overlay", ov)):
                cv2.imwrite(str(d / f"{name}.png"), im)
                rel[name] = f"job{job}/layer{i:04d}/{name}.png"
            if i == n_layers - 1:
                stack = np.zeros((size, size, 3), np.uint8)
                for k in range(n_layers):
                    y = size - 10 - int((size - 20) * k / max(1, n_layers))
                    col = (60, 60, 220) if fail_at is not None and k >= fail_at else (200, 170, 90)
                    cv2.rectangle(stack, (size // 4 + k // 4, y - 2), (3 * size // 4 + k // 4, y), col, -1)
                cv2.imwrite(str(d / "stack.png"), stack)
                rel["stack"] = f"job{job}/layer{i:04d}/stack.png"
        regions = []
        if blob > 0:
            regions = [Region(area_mm2=300 * ratio, bbox_mm=(112.0, 96.0, 120.0 + 8 * blob, 104.0 + 8 * blob),
                              centroid_mm=(116.0, 100.0), n_blocks=int(40 * ratio) + 1, mean_similarity=0.4)]
        res = LayerResult(layer=i, z=0.3 * (i + 1), metric=RECOMMENDED["analysis"]["metric"],
                          threshold=RECOMMENDED["analysis"]["threshold"], anomaly_ratio=ratio,
                          printed_area_mm2=400.0, anomalous_area_mm2=400.0 * ratio, n_blocks=120,
                          n_anomalous=int(120 * ratio), regions=regions,
                          timings_ms={"warp": 4.0, "render": 6.0, "hog": 3.0}, images=rel)
        history.add_layer(job, res)
        if ratio > 0.10 and not paused:
            paused = True
            history.add_event(job, "pause", f"a% {100 * ratio:.1f} % above 10 % at layer {i}: pause requested")
            history.add_event(job, "notification", f"notification sent: possible spaghetti at layer {i}")
    if outcome is not None:
        history.end_job(job, outcome)
    return job
