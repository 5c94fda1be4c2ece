"""One layer in, one :class:`~layerwatch.analysis.result.LayerResult` out.

:class:`LayerPipeline` chains the stages of the method for a job whose
G-code (toolpath), camera pose and config are known:

1. **warp** the photo into the top view of the layer's plane ``Z = z``
   (:class:`~layerwatch.geometry.warp.TopViewWarper`, eq. 3);
2. **reference**: render the ideal layer (:class:`~layerwatch.render.fast.StackRenderer`,
   incremental, memoised in memory and optionally on disk) as the camera sees
   it through the layer's plane (``render.view = "camera"``, the default:
   walls and the parallax of lower layers as in the warped photo, see
   :mod:`layerwatch.render.camera_view`), and optionally
   blur it by the camera's sampling footprint on that plane
   (:func:`~layerwatch.render.camera_match.match_camera`);
3. **analyse**: HOG of both images, similarity heatmap, anomaly ratio a%
   (eq. 5) and regions (:func:`~layerwatch.analysis.scoring.analyze_layer`).

The pipeline never raises for a bad photo or a failed warp: the result has
``status="error"`` and a one-line ``message``; a caller (monitor, CLI,
evaluation) logs it and goes on with the next layer. Configuration mistakes
made before any photo arrives (no pose, layer out of range) do raise.

References
----------
Petsiuk & Pearce (2022), Sections 2.3-2.4, eqs. (1)-(5).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from layerwatch.analysis.result import LayerResult
from layerwatch.config import JobConfig
from layerwatch.errors import LayerwatchError, RenderError
from layerwatch.gcode.toolpath import Toolpath
from layerwatch.geometry.camera import CameraModel

__all__ = ["LayerPipeline", "Reference"]


class Reference:
    """A reference of one layer as the pipeline uses it.

    Attributes
    ----------
    image : ndarray, shape (H, W), uint8
        Grey reference (camera-matched when the pipeline does that).
    footprint : ndarray, shape (H, W), bool
        Pixels printed in this layer.
    z : float
        Layer top, mm.
    """

    __slots__ = ("image", "footprint", "z")

    def __init__(self, image: np.ndarray, footprint: np.ndarray, z: float) -> None:
        self.image, self.footprint, self.z = image, footprint, float(z)


class LayerPipeline:
    """Analyse camera photos of a print layer by layer.

    Parameters
    ----------
    toolpath : Toolpath
        The job's parsed G-code.
    camera : CameraModel
        Calibrated camera with a bed pose (``rvec``/``tvec``).
    config : JobConfig, optional
        Top view, render and analysis settings (defaults when omitted).
    cache_dir : str or Path, optional
        Folder of an on-disk reference cache (:class:`~layerwatch.render.cache.ReferenceCache`);
        identical parts then render each layer once across runs.
    match_camera : bool
        Blur references by the camera's footprint on the layer plane (see
        :mod:`layerwatch.render.camera_match`). Off by default: on simulated
        photos it did not raise the share of clean blocks above cosine 0.7
        (75.5 % vs 75.7 %) and lowered detection (``docs/evaluation/README.md``).
    all_metrics : bool
        Score all twelve measures per layer into ``result.extra["per_metric"]``.
    memo : int
        References kept in memory (least recently used dropped).

    Raises
    ------
    LayerwatchError
        The camera has no pose or the toolpath has no layers.
    """

    def __init__(
        self,
        toolpath: Toolpath,
        camera: CameraModel,
        config: JobConfig | None = None,
        cache_dir: str | Path | None = None,
        *,
        match_camera: bool = False,
        all_metrics: bool = False,
        memo: int = 8,
    ) -> None:
        from layerwatch.geometry.warp import TopViewWarper
        from layerwatch.render.fast import StackRenderer

        if toolpath.n_layers == 0:
            raise RenderError(f"{toolpath.source} has no layers; check the G-code has extrusion moves.")
        self.toolpath = toolpath
        self.camera = camera
        self.config = config or JobConfig()
        self.topview = self.config.topview.topview()
        self.warper = TopViewWarper(camera, self.topview)
        self.renderer = StackRenderer(toolpath, self.topview, self.config.render)
        self.match_camera = bool(match_camera)
        self.all_metrics = bool(all_metrics)
        #: grey top view and valid mask of the last successfully warped photo (for overlays)
        self.last_top: np.ndarray | None = None
        self.last_valid: np.ndarray | None = None
        self._memo: OrderedDict[int, Reference] = OrderedDict()
        self._memo_size = max(1, int(memo))
        self._cache = None
        self._hash = None
        if cache_dir is not None:
            from layerwatch.render.cache import ReferenceCache, toolpath_hash

            self._cache = ReferenceCache(cache_dir)
            self._hash = toolpath_hash(toolpath)

    # ------------------------------------------------------------ references
    @property
    def view_center_mm(self) -> np.ndarray | None:
        """Camera centre the references are seen from (``render.view = "camera"``), else ``None``."""
        if self.config.render.view != "camera" or not self.camera.has_pose:
            return None
        return np.asarray(self.camera.center_mm, np.float64)

    def _render(self, index: int):
        c = self.view_center_mm
        if self._cache is None:
            return self.renderer.render(index, c)
        kind = "ref" if c is None else "cam:" + ",".join(f"{v:.3f}" for v in c)
        key = self._cache.key(self._hash, self.config.render, self.topview, index, kind=kind)
        return self._cache.get_or_render(key, lambda: self.renderer.render(index, c))

    def reference(self, index: int) -> Reference:
        """The (memoised) reference of layer ``index``.

        Raises
        ------
        RenderError
            ``index`` is not a layer of the toolpath.
        """
        n = self.toolpath.n_layers
        if not 0 <= index < n:
            raise RenderError(f"layer {index} does not exist (0..{n - 1}); check the photo's layer number.")
        hit = self._memo.get(index)
        if hit is not None:
            self._memo.move_to_end(index)
            return hit
        r = self._render(index)
        z = self.toolpath.layers[index].z
        image = r.image
        if self.match_camera:
            from layerwatch.render.camera_match import match_camera

            image = match_camera(image, self.camera, self.topview, z)
        ref = Reference(image, r.mask, z)
        self._memo[index] = ref
        while len(self._memo) > self._memo_size:
            self._memo.popitem(last=False)
        return ref

    def prepare(self, layers: Iterable[int] | None = None) -> None:
        """Render references ahead of the print (in increasing order, into the memo/cache).

        Only the last ``memo`` layers stay in memory; use ``cache_dir`` to keep all.
        """
        for i in sorted(range(self.toolpath.n_layers) if layers is None else layers):
            self.reference(int(i))

    # ------------------------------------------------------------ analysis
    def process(self, photo: np.ndarray, layer_index: int) -> LayerResult:
        """Analyse the photo taken after layer ``layer_index``.

        Parameters
        ----------
        photo : ndarray, uint8, shape (h, w) or (h, w, 3)
            Camera frame (BGR as cv2.imread gives, distorted as captured).
        layer_index : int
            0-based layer index in the toolpath.

        Returns
        -------
        LayerResult
            ``status`` ``"ok"``/``"skipped"``, or ``"error"`` with ``message``
            when the photo cannot be used (wrong type/shape, failed warp,
            nothing visible); ``timings_ms`` has ``warp``, ``reference``,
            ``analysis`` (and the analysis' own ``hog``, ``metric``,
            ``regions``) and ``total``.
        """
        t0 = time.perf_counter()
        st = self.config.analysis
        try:
            z = float(self.toolpath.layers[int(layer_index)].z) if 0 <= int(layer_index) < self.toolpath.n_layers else 0.0
        except (TypeError, ValueError):
            z = 0.0
        base = {"layer": int(layer_index) if isinstance(layer_index, (int, np.integer)) else -1, "z": z,
                "metric": st.metric, "threshold": float(st.threshold)}
        timings: dict[str, float] = {}
        self.last_top = self.last_valid = None
        t2 = t0
        try:
            ref = self.reference(int(layer_index))
            t1 = time.perf_counter()
            timings["reference"] = (t1 - t0) * 1e3
            top, valid = self.warper.warp(photo, ref.z)
            t2 = time.perf_counter()
            timings["warp"] = (t2 - t1) * 1e3
            if top.ndim == 3:
                top = top[..., :3].mean(axis=2).astype(np.uint8) if top.shape[2] > 1 else top[..., 0]
            if top.dtype != np.uint8:
                top = np.clip(top.astype(np.float32) / 257.0 if top.dtype == np.uint16 else top * 255.0,
                              0, 255).astype(np.uint8)
            if not valid.any():
                raise LayerwatchError("the photo does not show the observed area; check the camera pose.")
            res = _analyze(top, ref, valid, self, int(layer_index))
        except LayerwatchError as exc:
            return self._error(base, str(exc), timings, t0)
        except (ValueError, TypeError, IndexError, AttributeError, MemoryError) as exc:  # odd input
            return self._error(base, f"could not analyse the photo ({type(exc).__name__}: {exc}).", timings, t0)
        t3 = time.perf_counter()
        res.timings_ms = {**timings, "analysis": (t3 - t2) * 1e3,
                          **{k: v for k, v in res.timings_ms.items() if k != "total"},
                          "total": (t3 - t0) * 1e3}
        self.last_top, self.last_valid = top, valid
        return res

    @staticmethod
    def _error(base: dict, message: str, timings: dict, t0: float) -> LayerResult:
        res = LayerResult(status="error", message=message, **base)
        res.timings_ms = {**timings, "total": (time.perf_counter() - t0) * 1e3}
        return res


def _analyze(top: np.ndarray, ref: Reference, valid: np.ndarray, pipe: LayerPipeline,
                       layer: int) -> LayerResult:
    """Analyse one warped photo against its reference (raises LayerwatchError on bad input)."""
    from layerwatch.analysis.scoring import analyze_layer

    return analyze_layer(top, ref.image, ref.footprint, pipe.topview, pipe.config.analysis,
                         valid=valid, layer=layer, z=ref.z, all_metrics=pipe.all_metrics)
