"""Scene helpers shared by the geometry tests (imported as ``geometry_scenes``)."""

from __future__ import annotations

import cv2
import numpy as np

from layerwatch.geometry.camera import CameraModel
from layerwatch.geometry.synthetic import chessboard_texture, render_plane


def posed_camera(size=(960, 540), hfov_deg=65.0, eye=(0.0, -170.0, 190.0), target=(0.0, 0.0, 0.0),
                 dist=(-0.08, 0.02, 0.0, 0.0, 0.0)) -> CameraModel:
    """A camera at ``eye`` (bed mm) looking at ``target``; built here, independently of the code under test."""
    w, h = size
    f = (w / 2) / np.tan(np.deg2rad(hfov_deg) / 2)
    K = np.array([[f, 0, (w - 1) / 2 + 3.0], [0, f * 1.002, (h - 1) / 2 - 2.0], [0, 0, 1]])
    fwd = np.subtract(target, eye).astype(float)
    fwd /= np.linalg.norm(fwd)
    x = np.cross(fwd, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(fwd, x)
    R = np.stack([x, y, fwd])
    return CameraModel(K=K, dist=np.array(dist), image_size=size,
                       rvec=cv2.Rodrigues(R)[0].ravel(), tvec=-R @ np.asarray(eye, float))


def rotation_error_deg(a: CameraModel, b: CameraModel) -> float:
    c = (np.trace(a.R.T @ b.R) - 1) / 2
    return float(np.rad2deg(np.arccos(np.clip(c, -1, 1))))


K_TRUE = np.array([[620.0, 0, 322.0], [0, 618.0, 236.0], [0, 0, 1]])
DIST_TRUE = np.array([-0.12, 0.05, 0.0, 0.0, 0.0])


def _views(n: int, seed: int = 0):
    """Board photos (640x480) from ``n`` random tilted poses, noise and blur added."""
    rng = np.random.default_rng(seed)
    tex, A, corners = chessboard_texture(9, 6, 20.0, px_per_mm=8.0)
    centre = corners[:, :2].mean(0)
    out = []
    for _ in range(n):
        ax = rng.uniform(-0.45, 0.45, 3) * [1, 1, 0.3]
        R = cv2.Rodrigues(ax)[0]
        # board centre straight ahead at 300-380 mm, a little off axis
        t = np.array([rng.uniform(-25, 25), rng.uniform(-20, 20), rng.uniform(300, 380)]) - R @ [*centre, 0]
        cam = CameraModel(K=K_TRUE, dist=DIST_TRUE, image_size=(640, 480), rvec=cv2.Rodrigues(R)[0].ravel(), tvec=t)
        img = render_plane(cam, tex, A, background_rgb=(128, 128, 128), supersample=2)
        img = cv2.GaussianBlur(img, (0, 0), 0.7) + rng.normal(0, 2.0, img.shape)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out
