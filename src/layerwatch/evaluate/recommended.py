"""Settings recommended by the evaluation on simulated prints (``docs/evaluation/report.md``).

The paper's block threshold (T_S = 0.7 cosine) flags a large share of *clean*
blocks on our simulated camera photos (obliquely seen walls, bed texture,
bead noise), so offline runs and the demo use the values the evaluation
chose. They are merged *over* the job file's values (pass ``use_recommended=False``
to the commands that offer it to keep the file's own analysis settings).
"""

from __future__ import annotations

__all__ = ["RECOMMENDED", "recommended_config"]

#: per-section overrides (merged over a job config)
RECOMMENDED: dict[str, dict] = {
    "analysis": {"metric": "pearson", "threshold": 0.45, "footprint_margin_mm": 0.0,
                 "presmooth_px": 1.25, "grow_threshold": 0.2},
    "policy": {"pause_ratio": 0.04, "consecutive_layers": 2, "skip_first_layers": 1},
}


def recommended_config(path=None, **overrides):
    """``load_config(path)`` with :data:`RECOMMENDED` merged in, then ``overrides`` on top."""
    from layerwatch.config import load_config

    merged: dict[str, dict] = {k: dict(v) for k, v in RECOMMENDED.items()}
    for section, values in overrides.items():
        merged.setdefault(section, {}).update(values)
    return load_config(path, **merged)
