"""Volumetric view: unwrapped top views of successive layers stacked up (paper Fig. 7).

References
----------
Petsiuk & Pearce (2022), Fig. 7.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.errors import WarpError

__all__ = ["layer_array", "layer_stack"]


def _rgb(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img)
    if a.dtype != np.uint8:
        a = np.clip(a, 0, 255).astype(np.uint8)
    if a.ndim == 2:
        return np.repeat(a[..., None], 3, axis=2)
    if a.ndim == 3 and a.shape[2] >= 3:
        return a[..., :3]
    if a.ndim == 3 and a.shape[2] == 1:
        return np.repeat(a, 3, axis=2)
    raise WarpError(f"layer image has shape {a.shape}; pass (H, W) or (H, W, 3) top views.")


def layer_array(tops: list[np.ndarray], size: int | None = None) -> np.ndarray:
    """Stack top views into a grey volume, uint8 ``(L, H, W)`` (resized to ``size`` px wide if given)."""
    if len(tops) == 0:
        raise WarpError("no layers to stack; warp at least one photo first.")
    out = []
    for t in tops:
        g = _rgb(t)
        g = cv2.cvtColor(np.ascontiguousarray(g), cv2.COLOR_RGB2GRAY)
        if size is not None:
            g = cv2.resize(g, (size, max(1, round(size * g.shape[0] / g.shape[1]))), interpolation=cv2.INTER_AREA)
        out.append(g)
    if len({o.shape for o in out}) != 1:
        raise WarpError("layer images differ in size; warp them with the same top view.")
    return np.stack(out)


def layer_stack(tops: list[np.ndarray], *, mode: str = "oblique", size: int = 200, spacing_px: int = 6,
                skew: float = 0.5, squash: float = 0.45, background=(255, 255, 255),
                masks: list[np.ndarray] | None = None) -> np.ndarray:
    """Draw the stack of layer top views as one RGB image.

    Parameters
    ----------
    tops : list of ndarray, uint8, (H, W) or (H, W, 3)
        Top views, first layer first (all the same shape).
    mode : {"oblique", "strip"}
        ``"oblique"``: each layer as a sheared, flattened parallelogram drawn
        ``spacing_px`` above the previous one (Fig. 7); ``"strip"``: layers
        side by side left to right.
    size : int
        Width each layer is resized to, px.
    spacing_px : int
        Vertical distance between successive layers (oblique).
    skew, squash : float
        Horizontal shear and vertical flattening of each sheet (oblique).
    masks : list of bool (H, W) or None
        When given, pixels outside each mask are transparent (only the
        printed footprint of each layer is drawn), as in the paper.

    Returns
    -------
    ndarray, uint8, shape (h, w, 3)
    """
    if len(tops) == 0:
        raise WarpError("no layers to stack; warp at least one photo first.")
    layers = []
    for k, t in enumerate(tops):
        rgb = _rgb(t)
        h = max(1, round(size * rgb.shape[0] / rgb.shape[1]))
        rgb = cv2.resize(np.ascontiguousarray(rgb), (size, h), interpolation=cv2.INTER_AREA)
        m = None
        if masks is not None:
            m = cv2.resize(np.asarray(masks[k], np.uint8), (size, h), interpolation=cv2.INTER_NEAREST) > 0
        layers.append((rgb, m))
    if len({r.shape for r, _ in layers}) != 1:
        raise WarpError("layer images differ in size; warp them with the same top view.")
    h, w = layers[0][0].shape[:2]
    bg = np.asarray(background, np.uint8)
    if mode == "strip":
        gap = 4
        out = np.empty((h, len(layers) * (w + gap) - gap, 3), np.uint8)
        out[:] = bg
        for k, (rgb, m) in enumerate(layers):
            tile = out[:, k * (w + gap) : k * (w + gap) + w]
            if m is None:
                tile[:] = rgb
            else:
                tile[m] = rgb[m]
        return out
    if mode != "oblique":
        raise WarpError(f"unknown stack mode {mode!r}; use 'oblique' or 'strip'.")
    sh = max(1, round(h * squash))
    A = np.array([[1.0, skew * sh / h, 0.0], [0.0, squash, 0.0]])  # shear + flatten a sheet
    W = int(w + skew * sh) + 2
    Ht = sh + spacing_px * (len(layers) - 1) + 2
    out = np.empty((Ht, W, 3), np.uint8)
    out[:] = bg
    for k, (rgb, m) in enumerate(layers):  # bottom layer first, later layers drawn on top
        y0 = Ht - sh - 1 - k * spacing_px
        Ak = A.copy()
        Ak[1, 2] = y0
        alpha = np.full((h, w), 255, np.uint8) if m is None else m.astype(np.uint8) * 255
        sheet = cv2.warpAffine(rgb, Ak, (W, Ht), flags=cv2.INTER_LINEAR)
        a = cv2.warpAffine(alpha, Ak, (W, Ht), flags=cv2.INTER_LINEAR).astype(np.float32)[..., None] / 255.0
        out = (out * (1 - a) + sheet * a).astype(np.uint8)
        edge = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64) @ Ak[:, :2].T + Ak[:, 2]
        if m is None:
            cv2.polylines(out, [np.round(edge).astype(np.int32)], True, (90, 90, 90), 1, cv2.LINE_AA)
    return out
