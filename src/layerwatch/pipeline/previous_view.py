"""The print's previous photo, kept as the top view the step already made of it.

Series mode compares each photo with the one before it
(:class:`~layerwatch.analysis.part_registration.NewMaterial`: the edges that
are new since the previous photo, on the new layer's plane). Keeping the
previous photo itself costs 6 MB a printer at 1080p, most of a farm printer's
budget (10 MB), and warping it again onto the new plane costs a whole warp
(~4 ms at 1080p); only a few hundred kilobytes of it are ever read, and only
on the layers that have failing regions to type.

:class:`PreviousView` keeps the analysed photo's grey top view (its own
layer's plane, its residual view shift undone) on the rows and columns any
layer's registration crop can read (:func:`typing_area`: the print's reach
widened as :func:`~layerwatch.analysis.part_registration.crop_box` widens a
footprint; ~0.3 MB for the example part), a copy of what the step made anyway.
The next photo's typing asks for it on its own plane: the kept view is moved
there through the plane-to-plane homography (eqs. 1-3 of Petsiuk & Pearce
twice: top view -> undistorted image -> top view; the parallax of the layers
between, ~2 px a layer here), bilinear, unseen where the kept view ends (on
the kept plane itself the homography is the identity: the kept pixels).
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.analysis.part_registration import MOVE_MAX_MM, pad_box
from layerwatch.geometry.homography import image_from_top, top_from_image
from layerwatch.geometry.topview import TopView
from layerwatch.geometry.warp import TopViewWarper

__all__ = ["PreviousView", "typing_area"]


def typing_area(reach_mm: tuple[float, float, float, float] | None, topview: TopView) -> tuple[slice, slice]:
    """Top-view rows and columns that any layer's registration crop can read: the print's reach widened as
    :func:`~layerwatch.analysis.part_registration.crop_box` widens a footprint (and a pixel for rounding),
    clipped to the view; the whole view without a reach.

    Parameters
    ----------
    reach_mm : (xmin, ymin, xmax, ymax) or None
        Every segment's extent on the bed, mm (:func:`~layerwatch.pipeline.checks.print_reach_mm`).
    topview : TopView
    """
    h, w = topview.shape
    if reach_mm is None or not np.all(np.isfinite(reach_mm)):
        return slice(0, h), slice(0, w)
    (u0, v0), (u1, v1) = topview.to_px(np.array([reach_mm[:2], reach_mm[2:]], float))
    (v0, v1), (u0, u1) = sorted((v0, v1)), sorted((u0, u1))
    box = (int(np.floor(v0)), int(np.ceil(v1)) + 1, int(np.floor(u0)), int(np.ceil(u1)) + 1)
    return pad_box(box, int(np.ceil(MOVE_MAX_MM * topview.px_per_mm)) + 2, (h, w))


class PreviousView:
    """One analysed photo's grey top view on the print's surroundings (:meth:`keep`).

    Parameters
    ----------
    layer : int
        The photo's layer index.
    z : float
        The plane kept, mm (the photo's layer top).
    top : ndarray, uint8, shape (h, w)
        Grey top view of the photo on ``z`` as analysed (its residual view shift undone), rows and
        columns ``box``.
    valid : ndarray, bool, shape (h, w)
        Pixels of ``top`` the camera saw.
    box : (slice, slice)
        Where ``top`` lies in the whole top view, px.
    shift : (int, int)
        The photo's residual view shift ``(dx, dy)``, top-view px.
    """

    __slots__ = ("layer", "z", "_top", "_valid", "box", "shift")

    def __init__(self, layer: int, z: float, top: np.ndarray, valid: np.ndarray, box: tuple[slice, slice],
                 shift: tuple[int, int]) -> None:
        self.layer, self.z, self.box, self.shift = int(layer), float(z), box, (int(shift[0]), int(shift[1]))
        self._top = top
        self._valid = np.packbits(valid, axis=None)  # bits: the kept view's mask is an eighth of its pixels

    @property
    def nbytes(self) -> int:
        """Bytes of arrays held."""
        return int(self._top.nbytes + self._valid.nbytes)

    @classmethod
    def keep(cls, layer: int, z: float, top: np.ndarray, valid: np.ndarray, area: tuple[slice, slice],
             shift: tuple[int, int]) -> PreviousView:
        """Keep ``area`` of an analysed photo's top view.

        Parameters
        ----------
        layer : int
            The photo's layer index.
        z : float
            The plane of ``top``, mm (the layer's top).
        top : ndarray, uint8, shape (H, W)
            Grey top view as analysed (:func:`~layerwatch.analysis.view_shift.moved_back` applied).
        valid : ndarray, bool, shape (H, W)
            Pixels of ``top`` the camera saw.
        area : (slice, slice)
            Rows and columns kept (:func:`typing_area`).
        shift : (int, int)
            The photo's residual view shift ``(dx, dy)``, top-view px (what ``moved_back`` undid).
        """
        return cls(layer, z, np.array(top[area], np.uint8), np.asarray(valid, bool)[area], area, shift)

    def top(self, warper: TopViewWarper, z: float, box: tuple[slice, slice]) -> tuple[np.ndarray, np.ndarray] | None:
        """The kept photo as a grey top view of the plane ``z`` on ``box``, lying on the new photo's top view.

        Both top views are in the analysed frame (each photo's residual view shift undone): a top-view
        pixel ``p`` of the new plane is ``p + s`` of the kept photo's raw warp (``s`` its shift), which
        the planes' homography ``H`` takes to ``H (p + s)`` on the kept plane, ``H (p + s) - s`` in
        the kept view.

        Parameters
        ----------
        warper : TopViewWarper
            The pipeline's warper (its camera and top view).
        z : float
            The new photo's plane, mm.
        box : (slice, slice)
            Top-view rows and columns wanted.

        Returns
        -------
        (top, valid) or None
            Grey uint8 and bool, the shape of ``box``; None for an empty box. ``valid`` is False
            where the kept view did not reach or was unseen (every pixel a bilinear sample reads).
        """
        if box[0].stop <= box[0].start or box[1].stop <= box[1].start:
            return None
        r0, c0 = self.box[0].start, self.box[1].start
        kh, kw = self.box[0].stop - r0, self.box[1].stop - c0
        valid_kept = np.unpackbits(self._valid, count=kh * kw).view(bool).reshape(kh, kw)
        cam, tv = warper.camera, warper.topview
        dx, dy = self.shift
        planes = top_from_image(cam, tv, self.z) @ image_from_top(cam, tv, float(z))  # raw top(z) -> raw top(kept)
        M = (np.array([[1.0, 0, -dx - c0], [0, 1, -dy - r0], [0, 0, 1]]) @ planes
             @ np.array([[1.0, 0, box[1].start + dx], [0, 1, box[0].start + dy], [0, 0, 1]]))
        size = (box[1].stop - box[1].start, box[0].stop - box[0].start)
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        top = cv2.warpPerspective(self._top, M, size, flags=flags, borderValue=0)
        # seen where every pixel the bilinear sample reads was seen (an unseen one blends in its zero)
        seen = cv2.warpPerspective(valid_kept.astype(np.float32), M, size, flags=flags, borderValue=0) > 0.999
        top[~seen] = 0
        return top, seen
