"""A results folder of an offline run: per-layer JSON, overlays, stack, summary.

Layout (``layer_NNNN`` = 0-based layer index, zero-padded)::

    layers/layer_NNNN.json     LayerResult (heatmap included)
    overlays/layer_NNNN.png    heatmap overlay on the warped photo (paper Figs. 13, 15)
    tops/layer_NNNN.png        grey top view of the photo (for the layer stack)
    refs/layer_NNNN.png        the reference it was compared with
    stack.png                  the layer stack of all analysed top views
    summary.json, summary.md   table of every layer and the first pause

Every file is written to a temporary name and renamed, so an interrupted run
never leaves a half-written layer; :meth:`ResultsFolder.done` lists the layers
already finished, which a resumed run skips.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from layerwatch.analysis.overlay import overlay_image, region_label
from layerwatch.analysis.result import LayerResult
from layerwatch.geometry.stack import layer_stack
from layerwatch.geometry.topview import TopView

__all__ = ["ResultsFolder"]


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


class ResultsFolder:
    """Write and read back the results of a run.

    Parameters
    ----------
    root : str or Path
        Output folder (created).
    topview : TopView
        Geometry of the top views (for overlays).
    """

    def __init__(self, root: str | Path, topview: TopView) -> None:
        self.root = Path(root)
        self.topview = topview
        for sub in ("layers", "overlays", "tops", "refs", "masks"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)

    def _name(self, layer: int) -> str:
        return f"layer_{layer:04d}"

    def done(self) -> dict[int, LayerResult]:
        """Results already written, by layer (unreadable files are ignored, i.e. redone)."""
        out: dict[int, LayerResult] = {}
        for p in sorted((self.root / "layers").glob("layer_*.json")):
            try:
                res = LayerResult.from_json(p.read_text())
            except (ValueError, KeyError, TypeError):
                continue
            out[res.layer] = res
        return out

    def write(self, result: LayerResult, top: np.ndarray | None = None,
              footprint: np.ndarray | None = None, reference: np.ndarray | None = None) -> LayerResult:
        """Write one layer (overlay and top view only when ``top`` is given, the reference and footprint when given).

        ``tops/``, ``refs/`` and ``masks/`` hold what the comparison read, so
        ``layerwatch compare tops/X.png refs/X.png --mask masks/X.png`` re-runs one layer.
        """
        name = self._name(result.layer)
        if top is not None:
            ok, buf = cv2.imencode(".png", top)
            if ok:
                _atomic_write(self.root / "tops" / f"{name}.png", buf.tobytes())
                result.images["top"] = f"tops/{name}.png"
            if result.heatmap is not None:
                rgb = overlay_image(top, result, self.topview, footprint)
                ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
                if ok:
                    _atomic_write(self.root / "overlays" / f"{name}.png", buf.tobytes())
                    result.images["overlay"] = f"overlays/{name}.png"
        if reference is not None:
            ok, buf = cv2.imencode(".png", reference)
            if ok:
                _atomic_write(self.root / "refs" / f"{name}.png", buf.tobytes())
                result.images["reference"] = f"refs/{name}.png"
        if footprint is not None:
            ok, buf = cv2.imencode(".png", np.asarray(footprint, np.uint8) * 255)
            if ok:
                _atomic_write(self.root / "masks" / f"{name}.png", buf.tobytes())
                result.images["footprint"] = f"masks/{name}.png"
        _atomic_write(self.root / "layers" / f"{name}.json",
                      result.to_json(include_heatmap=True).encode())
        return result

    def stack(self, size: int = 220) -> Path | None:
        """Draw ``stack.png`` from the stored top views (None when there are none)."""
        read = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted((self.root / "tops").glob("layer_*.png"))]
        tops = [np.asarray(t) for t in read if t is not None]
        if not tops:
            return None
        img = layer_stack(tops, size=size, spacing_px=max(2, min(8, 600 // max(len(tops), 1))))
        path = self.root / "stack.png"
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[..., ::-1]))
        if ok:
            _atomic_write(path, buf.tobytes())
        return path

    def summary(self, results: dict[int, LayerResult], paused_at: int | None, reason: str = "",
                extra: dict | None = None) -> dict:
        """Write ``summary.json`` and ``summary.md``; returns the summary dict."""
        rows: list[dict[str, Any]] = []
        for layer in sorted(results):
            res = results[layer]
            rows.append({
                "layer": layer, "z": res.z, "status": res.status,
                "anomaly_ratio": None if res.status != "ok" else round(float(res.anomaly_ratio), 4),
                "regions": len(res.regions), "kind": region_label(res), "message": res.message,
                "ms": round(float(res.timings_ms.get("total", 0.0)), 1),
            })
        summary = {
            "layers": rows,
            "n_ok": sum(r["status"] == "ok" for r in rows),
            "n_error": sum(r["status"] == "error" for r in rows),
            "paused_at_layer": paused_at,
            "pause_reason": reason,
            **(extra or {}),
        }
        _atomic_write(self.root / "summary.json", json.dumps(summary, indent=1).encode())
        lines = ["# layerwatch run summary", ""]
        for k, v in (extra or {}).items():
            lines.append(f"- {k}: {v}")
        lines.append(f"- paused at layer: {paused_at if paused_at is not None else 'never'}"
                     + (f" ({reason})" if reason else ""))
        lines += ["", "| layer | z (mm) | status | a% | regions | failure | ms | note |",
                  "|---:|---:|---|---:|---:|---|---:|---|"]
        for r in rows:
            a = "" if r["anomaly_ratio"] is None else f"{100 * r['anomaly_ratio']:.1f}"
            mark = " **pause**" if paused_at == r["layer"] else ""
            lines.append(f"| {r['layer']} | {r['z']:.2f} | {r['status']}{mark} | {a} | {r['regions']} | {r['kind']} | "
                         f"{r['ms']} | {r['message']} |")
        _atomic_write(self.root / "summary.md", ("\n".join(lines) + "\n").encode())
        return summary
