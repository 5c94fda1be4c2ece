"""The empty-bed check: does the bed at job start look like the empty-bed photo?

Before the first layer, a leftover part, a tool or any object on the bed
ruins the print (the nozzle hits it, the part does not stick) and can damage
the printer. The camera is calibrated on the empty bed (``layerwatch
calibrate --markers`` keeps that photo), so at job start the same camera's
view of the bed plane ``Z = 0`` must match it up to the light:

1. both frames are warped to the top view of the bed plane (the caller's
   :class:`~layerwatch.geometry.warp.TopViewWarper`, eq. 3);
2. the light is fitted with the scene channel's photometric normalisation
   (:func:`~layerwatch.analysis.scene_change.photometric_fit`: a smooth
   per-channel ratio, robust to exposure, white balance and a lamp that moved);
3. the residual is scored per block with the scene channel's change test
   (:func:`~layerwatch.analysis.scene_change.change_blocks`: above the frame's
   own noise threshold and not explained by a local shade), and the changed
   blocks become regions in bed mm
   (:func:`~layerwatch.analysis.scene_change.change_regions`), typed
   ``foreign_body``;
4. at least ``min_area_mm2`` changed: the bed is **occupied**; a frame whose
   gain is out of range or that changed almost everywhere does not show the
   bed of the photo (camera moved or covered, light switched): the bed is
   **unchecked**, which is an alert, never a hold.

An object standing up from the bed appears in the bed-plane top view where
its footprint is and, stretched away from the camera, where its top is seen:
regions are where the camera sees the change on the bed plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from layerwatch.analysis.block_masks import blocks_to_pixels
from layerwatch.analysis.check_settings import BedCheckSettings
from layerwatch.analysis.result import Region
from layerwatch.analysis.scene_change import (
    SATURATED,
    change_blocks,
    change_regions,
    channel_max,
    photometric_fit,
    to_working,
)
from layerwatch.analysis.settings import SceneSettings
from layerwatch.geometry.topview import TopView

__all__ = ["BedCheck", "GAIN_RANGE", "check_empty_bed", "regions_image"]

#: photometric gains outside this range mean a frame that does not show the bed photo's scene
GAIN_RANGE = (0.4, 2.5)


@dataclass
class BedCheck:
    """The verdict of the empty-bed check.

    Attributes
    ----------
    status : str
        ``"clear"``, ``"occupied"`` (hold the job) or ``"unchecked"`` (the frame
        does not show the bed photo's scene; ``message`` says why).
    regions : list of Region
        Changed areas on the bed (bed mm, largest first), ``kind`` ``"foreign_body"``.
    changed_mm2 : float
        Their total area, mm^2.
    gain : tuple of float
        Photometric gain per channel (BGR) of the frame against the bed photo.
    changed_share : float
        Changed blocks over compared blocks.
    message : str
        One sentence for the operator.
    changed : ndarray, bool, shape (H, W)
        Changed top-view pixels (``topview`` geometry).
    """

    status: str
    regions: list[Region] = field(default_factory=list)
    changed_mm2: float = 0.0
    gain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    changed_share: float = 0.0
    message: str = ""
    changed: np.ndarray | None = None

    @property
    def occupied(self) -> bool:
        return self.status == "occupied"


def _change_settings(settings: BedCheckSettings) -> SceneSettings:
    """The scene channel's change-test settings with the bed check's block size and thresholds."""
    return SceneSettings(block_px=settings.block_px, noise_k=settings.noise_k, min_change=settings.min_change,
                         min_region_mm2=0.0)


def check_empty_bed(top: np.ndarray, bed_top: np.ndarray, topview: TopView, settings: BedCheckSettings,
                    valid: np.ndarray | None = None) -> BedCheck:
    """Compare the bed-plane top view at job start with the empty bed's (module notes).

    Parameters
    ----------
    top, bed_top : ndarray, uint8, shape (H, W, 3) or (H, W)
        Top views of the plane ``Z = 0`` of the job-start frame and of the empty-bed photo.
    topview : TopView
        Their geometry.
    settings : BedCheckSettings
    valid : ndarray, bool, shape (H, W), optional
        Top-view pixels the camera sees (default: where both images are not black).

    Returns
    -------
    BedCheck
    """
    size = (topview.shape[1], topview.shape[0])
    a, b = to_working(np.asarray(top), size), to_working(np.asarray(bed_top), size)
    seen = (channel_max(a) > 0) & (channel_max(b) > 0)
    if valid is not None:
        seen &= np.asarray(valid, bool)
    usable = seen & (channel_max(a) < SATURATED) & (channel_max(b) < SATURATED)
    ratio, gain = photometric_fit(a, b, usable)
    g = tuple(round(float(v), 4) for v in gain)
    if np.any(gain < GAIN_RANGE[0]) or np.any(gain > GAIN_RANGE[1]):
        return BedCheck("unchecked", gain=g, message=(  # type: ignore[arg-type]
            f"bed not checked: the camera's view does not match the empty-bed photo (photometric gain "
            f"{', '.join(f'{v:.2f}' for v in gain)}: dark, covered or overexposed?)"))
    ch = change_blocks(a, b, usable, ratio, _change_settings(settings))
    share = ch.changed_share
    if share > settings.max_changed_share:
        return BedCheck("unchecked", gain=g, changed_share=share, message=(  # type: ignore[arg-type]
            f"bed not checked: {share:.0%} of the view differs from the empty-bed photo (camera moved or "
            "covered, or the light changed); take a new bed photo with `layerwatch calibrate --markers`"))
    changed = ch.pixels(topview.shape) & usable
    sim = np.where(ch.changed, np.minimum(1.0, ch.threshold / np.maximum(ch.score, 1e-6)), 1.0)
    sim_px = blocks_to_pixels(np.asarray(sim, np.float32), ch.block_px, topview.shape, fill=1.0)
    regions = change_regions(changed, sim_px, topview, 0.0)
    for r in regions:
        r.kind, r.kind_confidence = "foreign_body", round(1.0 - r.mean_similarity, 3)
    area = float(sum(r.area_mm2 for r in regions))
    if area >= settings.min_area_mm2 and regions:
        big = regions[0]
        message = (f"the bed is not empty: {area:.0f} mm^2 differ from the empty-bed photo in {len(regions)} "
                   f"place(s), the largest ({big.area_mm2:.0f} mm^2) at ({big.centroid_mm[0]:.0f}, "
                   f"{big.centroid_mm[1]:.0f}) mm; clear the bed (leftover part, tool?) and resume")
        return BedCheck("occupied", regions, area, g, share, message, changed)  # type: ignore[arg-type]
    return BedCheck("clear", regions, area, g, share, "the bed is empty", changed)  # type: ignore[arg-type]


def regions_image(top: np.ndarray, regions: list[Region], topview: TopView, title: str,
                  mask: np.ndarray | None = None) -> np.ndarray:
    """The top view with ``regions`` boxed in red (and ``mask`` outlined), an RGB picture for the operator.

    Parameters
    ----------
    top : ndarray, uint8, shape (H, W, 3) BGR or (H, W)
    regions : list of Region
        Bed mm.
    topview : TopView
    title : str
        One line written at the top.
    mask : ndarray, bool, shape (H, W), optional
        Pixels to outline (the changed or missing area).

    Returns
    -------
    ndarray, uint8, shape (H, W, 3), RGB
    """
    img = np.asarray(top)
    rgb = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB) if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    rgb = np.ascontiguousarray(rgb)
    if mask is not None and mask.any():
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(rgb, contours, -1, (255, 200, 0), 1, lineType=cv2.LINE_AA)
    for r in regions:
        (u0, v0), (u1, v1) = np.round(topview.to_px(np.array([[r.bbox_mm[0], r.bbox_mm[3]],
                                                              [r.bbox_mm[2], r.bbox_mm[1]]]))).astype(int)
        cv2.rectangle(rgb, (int(u0) - 3, int(v0) - 3), (int(u1) + 3, int(v1) + 3), (255, 40, 40), 2)
    cv2.putText(rgb, title[:80], (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(rgb, title[:80], (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
    return rgb
