"""Give a top-view reference the resolution the camera actually has there.

A photo warped into the top view is sharp only to the extent that camera
pixels are small on the layer plane. Seen at ~45 deg, one camera pixel covers
an elongated ellipse of top-view pixels (foreshortened along the viewing
direction), so fine detail the fast renderer draws crisply — single beads,
infill lines — is smeared in the warped photo. HOG cells then see one sharp
orientation in the reference and a spread of orientations in the photo, and
clean layers lose similarity for reasons that are not failures.

:func:`match_camera` blurs the reference with the camera's own sampling
footprint: the Jacobian ``J`` of ``top_from_image`` at the observed point
maps a camera pixel's isotropic point-spread (``psf_px`` camera pixels, std)
to an anisotropic Gaussian in top-view pixels, ``Sigma_top = J Sigma_cam J^T``.
This is the reference "seen through the same camera", without rendering the
scene twice.

References
----------
Petsiuk & Pearce (2022), eqs. (1)-(3) (the plane homography whose Jacobian
is used here).
"""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.homography import apply_homography, image_from_top, top_from_image
from layerwatch.geometry.topview import TopView

__all__ = ["footprint_covariance", "match_camera"]


def footprint_covariance(
    camera: CameraModel,
    topview: TopView,
    z: float,
    at_mm: tuple[float, float] | None = None,
    psf_px: float = 0.6,
) -> np.ndarray:
    """Covariance, shape (2, 2), in top-view px^2, of one camera pixel's blur on plane ``z``.

    Parameters
    ----------
    camera : CameraModel
        Calibrated camera with pose.
    topview : TopView
        Top-view geometry.
    z : float
        Plane height, mm.
    at_mm : tuple of float, optional
        Bed point ``(x, y)`` where the footprint is evaluated; default the
        observed square's centre.
    psf_px : float
        Standard deviation of the camera's point-spread, camera pixels
        (optics + demosaicing + JPEG, ~0.5-1).
    """
    cam = camera
    c = topview.to_px(np.asarray(at_mm if at_mm is not None else topview.center_mm, float))
    H_it = image_from_top(cam, topview, z)
    H_ti = top_from_image(cam, topview, z)
    p = apply_homography(H_it, c[None])[0]
    eps = 0.5
    J = np.empty((2, 2))
    for k in range(2):
        d = np.zeros(2)
        d[k] = eps
        J[:, k] = (apply_homography(H_ti, (p + d)[None])[0] - apply_homography(H_ti, (p - d)[None])[0]) / (2 * eps)
    return (psf_px**2) * (J @ J.T)


def _gaussian_kernel(cov: np.ndarray) -> np.ndarray:
    w, _ = np.linalg.eigh(cov)
    sigma_max = float(np.sqrt(max(w.max(), 1e-12)))
    r = int(np.ceil(3.0 * sigma_max))
    r = max(1, min(r, 25))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1].astype(np.float64)
    inv = np.linalg.inv(cov + 1e-9 * np.eye(2))
    q = inv[0, 0] * xx * xx + 2 * inv[0, 1] * xx * yy + inv[1, 1] * yy * yy
    k = np.exp(-0.5 * q)
    return (k / k.sum()).astype(np.float32)


def match_camera(
    reference: np.ndarray,
    camera: CameraModel,
    topview: TopView,
    z: float,
    *,
    at_mm: tuple[float, float] | None = None,
    psf_px: float = 0.6,
    min_sigma_px: float = 0.35,
) -> np.ndarray:
    """Blur a top-view reference by the camera's sampling footprint on plane ``z``.

    Parameters
    ----------
    reference : ndarray, shape (H, W) or (H, W, 3), uint8 or float
        Reference image in the top view.
    camera, topview, z, at_mm, psf_px
        See :func:`footprint_covariance`.
    min_sigma_px : float
        Lower bound on the blur (top-view px) for the resampling of the warp.

    Returns
    -------
    ndarray, same shape and dtype as ``reference``.
    """
    cov = footprint_covariance(camera, topview, z, at_mm=at_mm, psf_px=psf_px)
    cov = cov + (min_sigma_px**2) * np.eye(2)
    kernel = _gaussian_kernel(cov)
    src = reference.astype(np.float32) if reference.dtype != np.float32 else reference
    out = cv2.filter2D(src, -1, kernel, borderType=cv2.BORDER_REPLICATE)
    if reference.dtype == np.uint8:
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)
    return out.astype(reference.dtype, copy=False)
