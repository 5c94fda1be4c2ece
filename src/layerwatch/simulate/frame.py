"""One simulated photo with its ground truth, and writing it to disk."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

__all__ = ["SimFrame", "save_frame"]


@dataclass
class SimFrame:
    """One simulated photo.

    Attributes
    ----------
    photo : ndarray, uint8, shape (h, w, 3)
        Camera view, BGR.
    truth : ndarray, bool, shape topview.shape, or None
        Where the layer differs from the plan (None: no failure active); exact
        footprints (e.g. the removed beads of an infill patch).
    truth_area : ndarray, bool, shape topview.shape, or None
        ``truth`` closed over gaps up to 3 mm (the failed *region*, e.g. the
        whole patch): the reference for localisation IoU. A shifted or
        detached layer's part of it is not closed again: it is where the
        layer's area (gaps of sparse infill closed) is and should not be and
        where it should be and is not.
    meta : dict
        ``layer``, ``z``, ``failures`` (active types), ``failed``, ``light``,
        ``exposure``, ``blur_px``, ``seconds``.
    """

    photo: np.ndarray
    truth: np.ndarray | None
    meta: dict = field(default_factory=dict)
    truth_area: np.ndarray | None = None

    @property
    def layer(self) -> int:
        return int(self.meta["layer"])


def save_frame(frame: SimFrame, folder, stem: str | None = None) -> dict:
    """Write a frame as ``<stem>.png`` (photo), ``<stem>_truth.png`` and ``<stem>_area.png``
    (masks, 0/255, only when a failure is active) and ``<stem>.json`` (meta).

    ``stem`` defaults to ``layer_<NNNN>``. Returns the written paths by kind.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stem = stem or f"layer_{frame.layer:04d}"
    out = {"photo": folder / f"{stem}.png", "meta": folder / f"{stem}.json"}
    cv2.imwrite(str(out["photo"]), frame.photo)
    if frame.truth is not None:
        out["truth"] = folder / f"{stem}_truth.png"
        cv2.imwrite(str(out["truth"]), frame.truth.astype(np.uint8) * 255)
        if frame.truth_area is not None:
            out["area"] = folder / f"{stem}_area.png"
            cv2.imwrite(str(out["area"]), frame.truth_area.astype(np.uint8) * 255)
    out["meta"].write_text(json.dumps(frame.meta, indent=1))
    return out
