"""A failure that stays, counts: where the scene's expected appearance keeps its old view.

After an accepted photo the scene model's expected appearance ``E``
(:class:`~layerwatch.pipeline.scene.SceneModel`) takes the photo on ``M``,
the layers printed since the last photo. An object lying on a small part's
top when that part printed a layer would become expected, and on the next
layer, when that part does not print (a plate of objects at interleaved
heights), nothing would see it. So on a layer whose HOG comparison alarmed
(the pipeline's test, :func:`~layerwatch.pipeline.policy.layer_alarm`) the
failing blocks (:func:`failing_blocks`) are *held*: projected into the
working image from the layer's plane (:func:`held_pixels`), their pixels
keep ``E``'s old appearance when the photo is taken into ``E``, and they
are judged even on the body's walls. They stay held while the next photos
show them changed and no later layer printed over them (:func:`still_held`:
there ``M`` covers them and the comparison judges them again), or until the
operator acknowledges the change
(:meth:`~layerwatch.pipeline.scene.SceneModel.acknowledge`).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from layerwatch.analysis.block_masks import whole_blocks
from layerwatch.analysis.overlay import anomalous_blocks
from layerwatch.analysis.result import LayerResult
from layerwatch.analysis.scene_change import top_coords

__all__ = ["failing_blocks", "held_pixels", "still_held"]


def failing_blocks(res: LayerResult, shape: tuple[int, int]) -> np.ndarray:
    """The pixels of a result's failing HOG blocks, whole blocks (not only their tiles), bool (H, W).

    Parameters
    ----------
    res : LayerResult
        With ``heatmap`` and ``grid`` (:func:`~layerwatch.analysis.overlay.anomalous_blocks`).
    shape : (H, W)
        The top view's shape, px.
    """
    assert res.heatmap is not None and res.grid is not None
    c, b = int(res.grid.cell_px), int(res.grid.block_cells)
    return whole_blocks(anomalous_blocks(res), shape, c, b)


def held_pixels(failing_top: np.ndarray, z: float, maps: tuple[np.ndarray, np.ndarray],
                full: Callable[[np.ndarray], np.ndarray], observed: np.ndarray) -> np.ndarray:
    """The failing blocks of the plane ``Z = z`` as the working image's pixels that see them.

    Parameters
    ----------
    failing_top : ndarray, bool, shape of the top view
        :func:`failing_blocks` of the layer.
    z : float
        Height of the layer's plane, mm.
    maps : (ndarray, ndarray)
        The scene model's plane maps (:func:`~layerwatch.analysis.scene_change.plane_maps`) on its
        reach box.
    full : callable
        A reach-box mask to a working-size one (False elsewhere).
    observed : ndarray, bool, (h, w)
        Working-image pixels that see the observed square.

    Returns
    -------
    ndarray, bool, (h, w)
    """
    mx, my = top_coords(maps, float(z))
    on = cv2.remap(np.asarray(failing_top, np.uint8), mx, my, cv2.INTER_NEAREST,
                   borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0
    return full(on) & observed


def still_held(held: np.ndarray | None, added: np.ndarray | None, predicted: np.ndarray | None,
               changed: np.ndarray | None) -> np.ndarray | None:
    """The held pixels after a photo: those held for its layer, and the earlier ones that it shows changed
    and that the layers since did not print over.

    Parameters
    ----------
    held : ndarray, bool, (h, w) or None
        Held before the photo.
    added : ndarray, bool, (h, w) or None
        Held for the photo's own layer (its failing blocks).
    predicted : ndarray, bool, (h, w) or None
        ``M`` of the photo (the layers printed since the last accepted one).
    changed : ndarray, bool, (h, w) or None
        The photo's changed blocks as working-image pixels.

    Returns
    -------
    ndarray, bool, (h, w) or None
        ``None`` when none is left.
    """
    out = added.copy() if added is not None else None
    if held is not None and predicted is not None and changed is not None:
        stays = held & ~predicted & changed
        out = stays if out is None else (out | stays)
    return out if out is not None and out.any() else None
