"""The print's previous photo, kept as the next layer's plane shows it.

Series mode compares each photo with the one before it
(:class:`~layerwatch.analysis.part_registration.NewMaterial`: the edges that
are new since the previous photo, on the new layer's plane). Keeping the
previous photo itself costs 6 MB a printer at 1080p, most of a farm printer's
budget (10 MB), and only a few hundred kilobytes of it are ever read: the top
view of the layer's surroundings on the next plane.

:class:`PreviousView` keeps exactly that. After a photo is analysed, its grey
top view of the next layer's plane is warped on the current footprint's
registration crop (:func:`~layerwatch.analysis.part_registration.crop_box`)
widened by :data:`GROWTH_MM`, offset by the photo's residual view shift as
:func:`~layerwatch.analysis.view_shift.moved_back` undoes it (~0.3 MB, uint8,
for the example part). When the next photo is of that layer (the usual case)
its box is read out of the kept view: the pixels of a warp of the previous
photo itself, bit for bit (a box's warp is the whole warp's pixels,
:meth:`~layerwatch.geometry.warp.TopViewWarper.warp`). For another plane (a
skipped layer, a photo retaken lower) the kept view is moved onto that plane
through the plane-to-plane homography (eq. 1-3 of Petsiuk & Pearce twice: top
view -> undistorted image -> top view), bilinear, with what it did not keep
marked unseen.
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.analysis.part_registration import MOVE_MAX_MM
from layerwatch.analysis.scoring import grey_u8
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
    pad = int(np.ceil(MOVE_MAX_MM * topview.px_per_mm)) + 2
    us, vs = sorted((u0, u1)), sorted((v0, v1))
    return (slice(max(int(np.floor(vs[0])) - pad, 0), min(int(np.ceil(vs[1])) + pad + 1, h)),
            slice(max(int(np.floor(us[0])) - pad, 0), min(int(np.ceil(us[1])) + pad + 1, w)))


class PreviousView:
    """One analysed photo's grey top view of the next layer's plane, on the part's surroundings.

    Parameters
    ----------
    layer : int
        The photo's layer index.
    z : float
        The plane kept, mm (the next layer's top).
    top : ndarray, uint8, shape (h, w)
        Grey top view of the photo on ``z``, rows and columns ``box`` of the warp of the raw photo
        (before the residual view shift is undone: :meth:`top` offsets the boxes it is asked for).
    valid : ndarray, bool, shape (h, w)
        Pixels of ``top`` the camera saw.
    box : (slice, slice)
        Where ``top`` lies in the whole top view of the raw photo, px.
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
    def capture(cls, warper: TopViewWarper, photo: np.ndarray, layer: int, z_next: float,
                area: tuple[slice, slice], shift: tuple[int, int]) -> PreviousView | None:
        """Keep ``photo`` (analysed as layer ``layer``) as the plane ``z_next`` shows it on ``area``.

        Parameters
        ----------
        warper : TopViewWarper
            The pipeline's warper.
        photo : ndarray, uint8, shape (h, w) or (h, w, 3)
            The camera frame as analysed.
        layer : int
        z_next : float
            The plane of the layer the next photo is expected of, mm.
        area : (slice, slice)
            Top-view rows and columns the next photo's typing may read, in the analysed frame
            (:func:`typing_area`).
        shift : (int, int)
            The photo's residual view shift ``(dx, dy)``, top-view px (:meth:`ViewShift.update
            <layerwatch.analysis.view_shift.ViewShift.update>`).

        Returns
        -------
        PreviousView or None
            None when ``area``, offset by the shift, is outside the view.
        """
        dx, dy = int(shift[0]), int(shift[1])
        h, w = warper.topview.shape
        # the raw photo's rows and columns that moved_back puts onto ``area`` (clipped to the view)
        box = (slice(max(area[0].start + dy, 0), min(area[0].stop + dy, h)),
               slice(max(area[1].start + dx, 0), min(area[1].stop + dx, w)))
        if box[0].stop <= box[0].start or box[1].stop <= box[1].start:
            return None
        top, valid = warper.warp(photo, z_next, box=box)
        return cls(layer, z_next, grey_u8(top), valid, box, (dx, dy))

    def top(self, warper: TopViewWarper, z: float, box: tuple[slice, slice]) -> tuple[np.ndarray, np.ndarray] | None:
        """The kept photo as a grey top view of the plane ``z`` on ``box``, its residual view shift undone.

        ``box`` is in the analysed photo's frame (its view shift undone): the kept photo's own shift
        is undone as :func:`~layerwatch.analysis.view_shift.moved_back` undid it (the box read from
        its warp is offset by it), so the result lies pixel for pixel on the new photo's top view.

        Returns
        -------
        (top, valid) or None
            Grey uint8 and bool, the shape of ``box``; None when the offset box leaves the view.
            On the kept plane and inside the kept box: the warp of the photo itself, bit for bit.
        """
        h, w = warper.topview.shape
        dx, dy = self.shift
        b = (slice(box[0].start + dy, box[0].stop + dy), slice(box[1].start + dx, box[1].stop + dx))
        if b[0].start < 0 or b[1].start < 0 or b[0].stop > h or b[1].stop > w:
            return None
        r0, c0 = self.box[0].start, self.box[1].start
        kh, kw = self.box[0].stop - r0, self.box[1].stop - c0
        valid_kept = np.unpackbits(self._valid, count=kh * kw).view(bool).reshape(kh, kw)
        if round(float(z), 4) == round(self.z, 4) and (r0 <= b[0].start and b[0].stop <= self.box[0].stop
                                                     and c0 <= b[1].start and b[1].stop <= self.box[1].stop):
            rows, cols = slice(b[0].start - r0, b[0].stop - r0), slice(b[1].start - c0, b[1].stop - c0)
            return self._top[rows, cols].copy(), valid_kept[rows, cols].copy()
        # another plane, or beyond the kept box: the kept view moved onto plane z (raw-photo frames both)
        cam, tv = warper.camera, warper.topview
        to_kept = top_from_image(cam, tv, self.z) @ image_from_top(cam, tv, float(z))
        M = (np.array([[1.0, 0, -c0], [0, 1, -r0], [0, 0, 1]]) @ to_kept
             @ np.array([[1.0, 0, b[1].start], [0, 1, b[0].start], [0, 0, 1]]))
        size = (b[1].stop - b[1].start, b[0].stop - b[0].start)
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        top = cv2.warpPerspective(self._top, M, size, flags=flags, borderValue=0)
        # seen where every pixel the bilinear sample reads was seen (an unseen one blends in its zero)
        seen = cv2.warpPerspective(valid_kept.astype(np.float32), M, size, flags=flags, borderValue=0) > 0.999
        top[~seen] = 0
        return top, seen
