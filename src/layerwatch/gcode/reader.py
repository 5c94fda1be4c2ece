"""``read_toolpath``: any slicer's G-code (text or .bgcode) -> :class:`Toolpath`."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from layerwatch.errors import GcodeError
from layerwatch.gcode import kernel as K
from layerwatch.gcode.layers import assign_layers
from layerwatch.gcode.tags import decode_tags, detect_slicer
from layerwatch.gcode.toolpath import Layer, Toolpath

__all__ = ["read_toolpath", "load_bytes", "run", "CHORD_TOL_MM"]

#: chord tolerance used to linearise G2/G3 arcs, mm
CHORD_TOL_MM = 0.01
_LH = re.compile(
    rb"(?:;\s*layer_height\s*=|;\s*layerHeight\s*[=:,]|<layerThickness>|;Layer height:)\s*([\d.]+)"
)
_FD = re.compile(rb";\s*filament_diameter\s*=\s*([\d.]+)")


def load_bytes(source: str | Path | bytes | bytearray | memoryview) -> tuple[bytes, str]:
    """Read ``source`` into bytes (decoding ``.bgcode``); returns ``(data, name)``."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        data, name = bytes(source), "<memory>"
    else:
        path = Path(source)
        name = str(path)
        if not path.is_file():
            raise GcodeError(f"{name}: no such G-code file; check the path.")
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise GcodeError(f"{name}: cannot read ({exc.strerror}); check permissions.") from exc
    if data[:4] == b"GCDE":
        from layerwatch.gcode.bgcode import decode_bgcode

        data = decode_bgcode(data, name)
    if not data.strip():
        raise GcodeError(f"{name}: the file is empty; slice the model again and export G-code.")
    head = data[:65536]
    if b"\x00" in head or sum(c < 9 or 13 < c < 32 for c in head[:4096]) > 16:
        pos = head.find(b"\x00")
        raise GcodeError(
            f"{name}: binary data at byte {max(pos, 0)}, not G-code text; export ASCII G-code from the slicer."
        )
    return data, name


_MODE = re.compile(rb"(?m)^[ \t]*(?:N\d+[ \t]*)?(?:M8[23]|G91|G92[^;\n]*E)(?![0-9])")
_EVAL = re.compile(rb"(?m)^G[01][ \t][^;\n]*E(-?[0-9.]+)")


def guess_relative_e(data: bytes) -> bool:
    """True when a file never sets the E mode yet its E values are relative (e.g. Kiri:Moto)."""
    if _MODE.search(data):
        return False
    vals = np.array([float(v) for v in _EVAL.findall(data[:262144])[:4000] if v not in (b"-", b".")])
    return vals.size > 20 and float(np.mean(np.diff(vals) > 0)) < 0.5


def run(data: bytes, probes: np.ndarray | None = None):
    """Run the numba kernel over ``data`` (see :func:`layerwatch.gcode.kernel.run_kernel`)."""
    buf = np.frombuffer(data, dtype=np.uint8)
    if probes is None:
        probes = np.zeros(0, np.int64)
    return K.run_kernel(
        buf, np.ascontiguousarray(probes, np.int64), CHORD_TOL_MM, guess_relative_e(data)
    )


def _bead_width(seg: np.ndarray, height: np.ndarray, d: float) -> np.ndarray:
    """Rounded-rectangle bead width from filament used, mm."""
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    area = seg[:, 5] * (np.pi * d * d / 4.0) / np.maximum(length, 1e-9)
    h = np.maximum(height, 1e-3)
    w = area / h + h * (1.0 - np.pi / 4.0)
    return np.clip(w, 0.0, 10.0 * d).astype(np.float32)


def read_toolpath(
    source: str | Path | bytes,
    *,
    filament_diameter: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Toolpath:
    """Parse G-code into per-layer extruding segments.

    Parameters
    ----------
    source : str, Path or bytes
        A ``.gcode``/``.bgcode`` file or its bytes.
    filament_diameter : float, optional
        Filament diameter in mm; default from the file header, else 1.75.
    progress : callable(done_bytes, total_bytes), optional
        Called as parsing advances.

    Returns
    -------
    Toolpath
        Segments in bed mm; ``detection`` says how layers were found.

    Raises
    ------
    GcodeError
        Empty, binary or unreadable input (message names the file and the fix).
    """
    data, name = load_bytes(source)
    total = len(data)
    if progress:
        progress(0, total)
    seg, seg_line, seg_tool, travel_line, cmt, _probe, st = run(data)
    if progress:
        progress(int(total * 0.9), total)
    warnings: list[str] = []
    short = Path(name).name
    if st[K.ST_BAD]:
        warnings.append(
            f"{short}:{st[K.ST_FIRST_BAD]}: {st[K.ST_BAD]} line(s) with non-text bytes were ignored"
        )
    if st[K.ST_ABSURD]:
        warnings.append(
            f"{short}:{st[K.ST_FIRST_ABSURD]}: {st[K.ST_ABSURD]} move(s) beyond {K.ABSURD_MM:g} mm (absurd coordinates)"
        )
    if st[K.ST_ARC_BAD]:
        warnings.append(
            f"{short}:{st[K.ST_FIRST_ARC_BAD]}: {st[K.ST_ARC_BAD]} arc(s) without I/J or R drawn as lines"
        )
    last = data[data.rfind(b"\n") + 1 :].lstrip().upper()
    if st[K.ST_NONL] and re.match(rb"G0?[0-3](?![0-9])", last):
        warnings.append(f"{short}:{st[K.ST_LINES]}: the file ends mid-line; it may be truncated")
    buf = memoryview(data)
    tags = decode_tags(buf, cmt)
    head = data[:8192]
    slicer = detect_slicer(head)
    if filament_diameter is None:
        m = _FD.search(data[-65536:]) or _FD.search(head)
        filament_diameter = float(m.group(1).split(b",")[0]) if m else 1.75
        if not 0.5 <= filament_diameter <= 5:
            filament_diameter = 1.75
    m = _LH.search(head) or _LH.search(data[-65536:])
    lh_hint = float(m.group(1)) if m else None
    bounds, lz, detection, w2 = assign_layers(
        seg[:, 4], seg_line, tags.layer_lines, tags.layer_z, tags.style, lh_hint, seg[:, 2:4]
    )
    warnings += w2
    n = seg.shape[0]
    if n == 0:
        warnings.append(f"{short}: no extruding moves found (not a 3D-printer file, or E is never used)")
    heights = np.diff(np.concatenate([[0.0], lz]))
    good = heights[heights > 0.01]
    fallback_h = float(np.median(good)) if good.size else 0.2
    heights = np.where(heights > 0.01, heights, fallback_h)
    if len(heights) and lz[0] > 0:
        heights[0] = min(lz[0], 2.0) if lz[0] > 0.01 else fallback_h
    counts = np.diff(bounds)
    seg_h = np.repeat(heights, counts)
    if tags.feature_lines.size:
        fi = np.searchsorted(tags.feature_lines, seg_line, side="right") - 1
        feature = np.where(fi >= 0, tags.feature_codes[np.maximum(fi, 0)], 0).astype(np.uint8)
    else:
        feature = np.zeros(n, np.uint8)
    n_lines = int(st[K.ST_LINES])
    layers = []
    prev_stop = 1
    for k in range(len(lz)):
        a, b = int(bounds[k]), int(bounds[k + 1])
        if detection.startswith("tags") and k > 0:
            tl = tags.layer_lines
            j = int(np.searchsorted(tl, seg_line[a], side="right")) - 1
            start = int(tl[j]) if j >= 0 else int(seg_line[a])
        else:
            start = prev_stop if k == 0 else int(seg_line[bounds[k - 1] + counts[k - 1] - 1]) + 1
        start = max(start, prev_stop if k else 1)
        layers.append(start)
        prev_stop = start
    layer_objs = []
    for k in range(len(lz)):
        a, b = int(bounds[k]), int(bounds[k + 1])
        stop = layers[k + 1] if k + 1 < len(lz) else n_lines + 1
        s = seg[a:b]
        xs = np.concatenate([s[:, 0], s[:, 2]])
        ys = np.concatenate([s[:, 1], s[:, 3]])
        n_trav = int(
            np.searchsorted(travel_line, stop, "left") - np.searchsorted(travel_line, layers[k], "left")
        )
        layer_objs.append(
            Layer(
                index=k,
                z=float(lz[k]),
                height=float(heights[k]),
                seg_start=a,
                seg_stop=b,
                line_start=int(layers[k]),
                line_stop=int(stop),
                bounds=(float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())),
                extrusion_mm=float(s[:, 5].sum()),
                n_travel=n_trav,
            )
        )
    tp = Toolpath(
        start=np.ascontiguousarray(seg[:, 0:2]),
        end=np.ascontiguousarray(seg[:, 2:4]),
        z=np.ascontiguousarray(seg[:, 4]),
        e=np.ascontiguousarray(seg[:, 5]),
        width=_bead_width(seg, seg_h, filament_diameter),
        feature=feature,
        tool=seg_tool,
        line=seg_line,
        layers=tuple(layer_objs),
        detection=detection,
        filament_diameter=float(filament_diameter),
        source=name,
        slicer=slicer,
        warnings=warnings,
    )
    if progress:
        progress(total, total)
    return tp
