"""Self-contained HTML report of one job from the history.

The page embeds every picture as base64 (a% curve drawn with matplotlib,
overlays of the first failing and the worst layers, the layer stack if one
was stored), so the single ``report.html`` can be mailed or archived.
"""

from __future__ import annotations

import base64
import html
import io
import time
from pathlib import Path

from matplotlib.figure import Figure

from layerwatch.analysis.overlay import region_label
from layerwatch.errors import StorageError
from layerwatch.pipeline.policy import STOPPING
from layerwatch.storage.history import History

__all__ = ["build_report", "curve_png"]


def curve_png(layers: list[int], ratios: list[float | None], pause_ratio: float | None) -> bytes:
    """The a% curve over layers with the pause threshold, as PNG bytes.

    Parameters
    ----------
    layers : list of int
        Layer indices.
    ratios : list of float or None
        Anomaly ratio a% per layer as fractions in [0, 1] (None: not analysed).
    pause_ratio : float or None
        Threshold drawn as a dashed red line (fraction).
    """
    fig = Figure(figsize=(8, 3), dpi=100)
    ax = fig.add_subplot()
    pts = [(layer, 100 * r) for layer, r in zip(layers, ratios, strict=True) if r is not None]
    if pts:
        ax.plot([p[0] for p in pts], [p[1] for p in pts], color="#2563eb", lw=1.8, label="a% per layer")
    if pause_ratio is not None:
        ax.axhline(100 * pause_ratio, color="#dc2626", ls="--", lw=1.2, label=f"pause threshold {100 * pause_ratio:.1f} %")
    ax.set_xlabel("layer")
    ax.set_ylabel("anomalous area a% (%)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _img_tag(data: bytes, alt: str, mime: str = "image/png") -> str:
    return f'<img alt="{html.escape(alt)}" src="data:{mime};base64,{base64.b64encode(data).decode()}">'


def _file_tag(root: Path | None, rel: str | None, alt: str) -> str:
    if not rel or root is None:
        return f'<p class="missing">{html.escape(alt)}: not stored</p>'
    path = (root / rel).resolve()
    if not path.is_relative_to(root.resolve()) or not path.is_file():
        return f'<p class="missing">{html.escape(alt)}: file {html.escape(rel)} missing</p>'
    mime = "image/jpeg" if path.suffix.lower() in (".jpg", ".jpeg") else "image/png"
    return _img_tag(path.read_bytes(), alt, mime)


_CSS = """body{font:15px/1.4 system-ui,sans-serif;max-width:1000px;margin:auto;padding:1rem;color:#1f2937}
img{max-width:100%}.row{display:grid;grid-template-columns:repeat(auto-fit,minmax(220px,1fr));gap:.6rem}
figure{margin:0}figure img{width:100%}figcaption{text-align:center;color:#6b7280}.fail{color:#dc2626;font-weight:600}
.missing{color:#6b7280;font-style:italic}table{border-collapse:collapse}td,th{padding:.2rem .6rem;border-bottom:1px solid #eee}"""


def build_report(history: History, job_id: int, out_dir: str | Path, image_root: str | Path | None = None) -> Path:
    """Write ``out_dir/report.html`` for ``job_id`` and return its path.

    Parameters
    ----------
    history : History
        The history database.
    job_id : int
        Job to report.
    out_dir : str or Path
        Folder to write into (created).
    image_root : str or Path, optional
        Folder the layers' image paths are relative to (default: next to the
        database file).

    Raises
    ------
    StorageError
        Unknown job.
    """
    job = history.job(job_id)
    if job is None:
        raise StorageError(f"no job {job_id} in the history; list jobs with `layerwatch history`.")
    root = Path(image_root) if image_root is not None else (history.path.parent if history.path else None)
    results = history.layers(job_id)
    events = history.events(job_id)
    cfg = job.get("config") or {}
    pause = (cfg.get("policy") or {}).get("pause_ratio")
    if pause is None and results:
        pause = 0.10
    first = next((r for r in results if pause is not None and r.status == "ok"
                  and (r.anomaly_ratio > pause or r.decision in STOPPING)), None)
    worst = max((r for r in results if r.status == "ok"), key=lambda r: r.anomaly_ratio, default=None)
    curve = curve_png([r.layer for r in results], [r.anomaly_ratio if r.status == "ok" else None for r in results], pause)

    def layer_block(r, title: str) -> str:
        im = r.images or {}
        figs = "".join(
            f"<figure>{_file_tag(root, im.get(k), k)}<figcaption>{k}</figcaption></figure>"
            for k in ("top", "reference", "overlay")
        )
        label = region_label(r)
        kind = f", largest: {html.escape(label)}" if label else ""
        return (f"<h3>{html.escape(title)}: layer {r.layer} (z {r.z:.2f} mm), a% {100 * r.anomaly_ratio:.1f} %, "
                f"{len(r.regions)} region(s){kind}</h3><div class='row'>{figs}</div>")

    stack_rel = next((r.images.get("stack") for r in reversed(results) if r.images and r.images.get("stack")), None)
    started = time.strftime("%Y-%m-%d %H:%M", time.localtime(job["started"]))
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><meta name='viewport' content='width=device-width'>"
        f"<title>layerwatch report job {job_id}</title><style>{_CSS}</style></head><body>",
        f"<h1>Job #{job_id}: {html.escape(job.get('part') or '')}</h1>",
        f"<table><tr><th>printer</th><td>{html.escape(job['printer'])}</td></tr>"
        f"<tr><th>started</th><td>{started}</td></tr><tr><th>outcome</th><td>{html.escape(job.get('outcome') or 'running')}</td></tr>"
        f"<tr><th>G-code</th><td>{html.escape(job.get('gcode_path') or '')} {html.escape((job.get('gcode_hash') or '')[:12])}</td></tr>"
        f"<tr><th>layers analysed</th><td>{len(results)}</td></tr></table>",
        "<h2>Anomaly ratio over layers</h2>", _img_tag(curve, "a% curve"),
        "<h2>First failing layer</h2>",
        (f"<p class='fail'>layer {first.layer} (a% {100 * first.anomaly_ratio:.1f} %"
         + (f", pause threshold {100 * pause:.1f} %" if pause is not None else "")
         + f"; {first.outside_anomalous_mm2:.0f} mm^2 changed beside the print)</p>"
         if first is not None else "<p>none: every layer stayed under the pause threshold</p>"),
    ]
    if first:
        parts.append(layer_block(first, "First failing layer"))
    if worst and worst is not first:
        parts.append(layer_block(worst, "Worst layer"))
    parts.append("<h2>Layer stack</h2>" + (_file_tag(root, stack_rel, "layer stack") if stack_rel else "<p class='missing'>no stack image stored</p>"))
    parts.append("<h2>Events</h2><ol>" + "".join(
        f"<li>{time.strftime('%H:%M:%S', time.localtime(e['time']))} <b>{html.escape(e['kind'])}</b> {html.escape(e['message'])}</li>"
        for e in events) + "</ol></body></html>")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.html"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
