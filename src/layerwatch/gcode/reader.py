"""``read_toolpath``: any slicer's G-code (text or .bgcode) -> :class:`Toolpath`."""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from layerwatch.errors import GcodeError
from layerwatch.gcode import kernel_abi as K
from layerwatch.gcode.bgcode import decode_bgcode
from layerwatch.gcode.generators import detect_generator
from layerwatch.gcode.gx import MAGIC as GX_MAGIC
from layerwatch.gcode.gx import decode_gx
from layerwatch.gcode.layers import assign_layers
from layerwatch.gcode.native import KernelOutput, run_kernel
from layerwatch.gcode.statements import Statements, read_statements
from layerwatch.gcode.tags import decode_tags
from layerwatch.gcode.toolpath import FEATURES, Layer, Toolpath, part_mask

__all__ = ["read_toolpath", "load_bytes", "run", "CHORD_TOL_MM"]

#: chord tolerance used to linearise G2/G3 arcs, mm
CHORD_TOL_MM = 0.01
_LH = re.compile(
    rb"(?:;\s*layer_height\s*=|;\s*layerHeight\s*[=:,]|<layerThickness>|;Layer height:)\s*([\d.]+)"
)


def _finite(raw: bytes) -> float | None:
    """A finite float from header bytes such as ``b"0.2"``; None for ``b"1.2.3"`` and the like."""
    try:
        v = float(raw)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


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
        data = decode_bgcode(data, name)
    elif data[: len(GX_MAGIC)] == GX_MAGIC:
        data = decode_gx(data, name)
    if not data or data.isspace():
        raise GcodeError(f"{name}: the file is empty; slice the model again and export G-code.")
    head = data[:65536]
    codes = np.frombuffer(head[:4096], np.uint8)
    if b"\x00" in head or int(np.count_nonzero((codes < 9) | ((codes > 13) & (codes < 32)))) > 16:
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
    vals = np.array([v for v in map(_finite, _EVAL.findall(data[:262144])[:4000]) if v is not None])
    return vals.size > 20 and float(np.mean(np.diff(vals) > 0)) < 0.5


def volumetric_area(st: Statements, filament_diameter: float) -> float:
    """Filament cross-section (mm²) when the file's E words are volumes from the start, else 0.

    Cura's UltiGCode flavour (Ultimaker 2) writes E in mm³; RepRapFirmware's
    ``M200 D<d>`` switches to volumes inside the file (handled by the kernel).
    """
    if st.flavor and st.flavor.lower() == "ultigcode":
        return float(np.pi * filament_diameter**2 / 4.0)
    return 0.0


def kernel_outputs(data: bytes, probes: np.ndarray | None = None, e_area: float = 0.0) -> KernelOutput:
    """Raw kernel outputs for ``data`` (see :class:`layerwatch.gcode.native.KernelOutput`)."""
    if probes is None:
        probes = np.zeros(0, np.int64)
    return run_kernel(data, probes, CHORD_TOL_MM, guess_relative_e(data), float(e_area))


def run(data: bytes, probes: np.ndarray | None = None) -> tuple:
    """Kernel outputs in a compact form for tests and the post-processor.

    Returns
    -------
    seg : (S, 6) float64  x0, y0, x1, y1, z, e
    seg_line, seg_tool, travel_line, cmt, probe_state, stats : see the kernel
    """
    ko = kernel_outputs(data, probes)
    segf = np.column_stack([ko.start, ko.end, ko.z, ko.e])
    return segf, ko.line, ko.tool, ko.travel_line, ko.cmt, ko.probe_state, ko.stats


def _line_text(data: bytes, line: int, limit: int = 60) -> str:
    """Text of 1-based ``line`` of ``data`` (for messages), shortened to ``limit`` characters."""
    nl = np.flatnonzero(np.frombuffer(data, np.uint8) == 10)
    a = int(nl[line - 2]) + 1 if 2 <= line <= nl.size + 1 else 0
    b = int(nl[line - 1]) if line - 1 < nl.size else len(data)
    text = data[a:b].decode("latin-1").strip()
    return repr(text if len(text) <= limit else text[: limit - 3] + "...")


def _bead_width(
    a: np.ndarray, b: np.ndarray, e: np.ndarray, height: np.ndarray, d: float
) -> np.ndarray:
    """Rounded-rectangle bead width from filament used, mm, float32 (S,).

    ``w = A / h + h (1 - pi/4)`` with bead area ``A = e * pi d^2 / 4 / length``.
    """
    d_ = (b - a).astype(np.float32)
    length = np.hypot(d_[:, 0], d_[:, 1])
    del d_
    w = e.astype(np.float32)
    w *= np.float32(np.pi * d * d / 4.0)
    w /= np.maximum(length, np.float32(1e-9))
    h = np.maximum(height, 1e-3).astype(np.float32)
    w /= h
    w += h * np.float32(1.0 - np.pi / 4.0)
    return np.clip(w, 0.0, 10.0 * d, out=w)


def _layer_thickness(lz: np.ndarray, lo: np.ndarray | None, hi: np.ndarray | None,
                     bounds: np.ndarray) -> np.ndarray:
    """Bead thickness of each layer: its Z minus that of the last lower layer printed under it, mm (L,).

    Usually the step from the previous layer. Where objects are printed at
    interleaved heights (KISSlicer's per-object layers: 0.263, 0.278, 0.526,
    0.556 ... mm) the previous layer is another object's, and the 0.015 mm
    step would make the beads several mm wide; "under it" is the last lower
    layer whose bounding box (``lo``, ``hi``: (L, 2) corners, mm) overlaps this
    one's (the bed when there is none).
    """
    n = len(lz)
    steps = np.diff(np.concatenate([[0.0], lz]))
    if n < 2 or lo is None or hi is None or len(bounds) != n + 1:
        return steps
    nonempty = np.diff(bounds) > 0
    # the common case, vectorised: the previous layer overlaps this one
    prev_ok = np.zeros(n, bool)
    prev_ok[1:] = ((lo[:-1] <= hi[1:]) & (lo[1:] <= hi[:-1])).all(axis=1) & nonempty[:-1] & nonempty[1:]
    out = steps.copy()
    for k in (np.flatnonzero(~prev_ok[1:] & nonempty[1:]) + 1).tolist():
        below = 0.0
        for j in range(k - 1, max(k - 200, -1), -1):
            if nonempty[j] and lz[j] < lz[k] and (lo[j] <= hi[k]).all() and (lo[k] <= hi[j]).all():
                below = float(lz[j])
                break
        out[k] = min(float(lz[k]) - below, 2.0)
    return out


def _kernel_warnings(data: bytes, short: str, st: np.ndarray) -> list[str]:
    """One ``file:line: text`` warning per kind of problem the kernel counted."""
    kinds = (
        (K.ST_BAD, K.ST_FIRST_BAD, "line(s) with non-text bytes; those bytes were ignored"),
        (K.ST_MALFORMED, K.ST_FIRST_MALFORMED,
         "line(s) with a malformed number or stray character; what could not be read was ignored"),
        (K.ST_ABSURD, K.ST_FIRST_ABSURD,
         f"move(s) beyond {K.ABSURD_MM:g} mm (absurd coordinates; check units); not drawn"),
        (K.ST_ARC_BAD, K.ST_FIRST_ARC_BAD,
         "arc(s) without a usable centre (no I/J or R, or an absurd radius) drawn as straight lines"),
        (K.ST_ARC_CAPPED, K.ST_FIRST_ARC_CAPPED,
         f"arc(s) linearised with fewer chords than the {CHORD_TOL_MM:g} mm tolerance asks "
         "(chord count bounded by the arc's length and the file's budget)"),
    )
    out = [
        f"{short}:{st[first]}: {_line_text(data, st[first])}: {st[count]} {text}"
        for count, first, text in kinds
        if st[count]
    ]
    last = data[data.rfind(b"\n") + 1 :].lstrip().upper()
    if st[K.ST_NONL] and re.match(rb"G0?[0-3](?![0-9])", last):
        out.append(
            f"{short}:{st[K.ST_LINES]}: {_line_text(data, st[K.ST_LINES])}: the file ends mid-move; "
            "it may be truncated (export or copy it again)"
        )
    return out


def _filament_diameter(given: float | None, st: Statements) -> float:
    """The caller's diameter, else the file's, else 2.85 mm for UltiGCode and 1.75 mm otherwise."""
    if given is not None:
        if not (math.isfinite(given) and 0.5 <= given <= 5.0):
            raise GcodeError(f"filament diameter {given!r} mm is out of range; pass 1.75 or 2.85 (0.5 .. 5 mm).")
        return float(given)
    if st.filament_diameter is not None:
        return st.filament_diameter
    return 2.85 if (st.flavor or "").lower() == "ultigcode" else 1.75


def _features(tags, seg_line: np.ndarray, seg_z: np.ndarray, detection: str, bounds: np.ndarray) -> np.ndarray:
    """Feature code per segment: the slicer's tags; moves before the first layer starts
    (start G-code purge and prime lines) are ``purge``."""
    n = seg_line.shape[0]
    # seg_line is sorted: each tag's first segment is one binary search, then runs are repeated
    first = np.searchsorted(seg_line, tags.feature_lines, side="left")
    codes = np.concatenate([[0], tags.feature_codes]).astype(np.uint8)
    feature = np.repeat(codes, np.diff(np.concatenate([[0], first, [n]])))
    n_purge = 0
    if detection.startswith("tags") and tags.layer_lines.size:
        n_purge = int(np.searchsorted(seg_line, tags.layer_lines[0], side="left"))
    elif detection == "z" and len(bounds) > 1:  # prime lines above layer 0, merged into it by assign_layers
        z0 = seg_z[bounds[0] : bounds[1]]
        on_layer = np.flatnonzero(np.abs(z0 - z0.min()) < 1e-4)
        n_purge = int(on_layer[0]) if on_layer.size else 0
    feature[:n_purge] = FEATURES.index("purge")
    return feature


def _layer_boxes(seg_a, seg_b, seg_e, feature, bounds):
    """Per-layer part box (L, 2) lo/hi (not-part features left out unless alone) and extrusion (L,).

    All segments are reduced per layer at once; only the layers that hold skirt, brim, purge
    or wipe-tower segments are redone on their part segments.
    """
    idx = bounds[:-1]
    lo = np.minimum(np.minimum.reduceat(seg_a, idx, axis=0), np.minimum.reduceat(seg_b, idx, axis=0))
    hi = np.maximum(np.maximum.reduceat(seg_a, idx, axis=0), np.maximum.reduceat(seg_b, idx, axis=0))
    part = part_mask(feature)
    if not part.all():
        mixed = np.flatnonzero(np.add.reduceat((~part).astype(np.int64), idx) > 0)
        for k in mixed:
            a, b = bounds[k], bounds[k + 1]
            keep = part[a:b]
            if keep.any():  # a layer of skirt or purge only keeps the box of what is there
                pa, pb = seg_a[a:b][keep], seg_b[a:b][keep]
                lo[k] = np.minimum(pa.min(axis=0), pb.min(axis=0))
                hi[k] = np.maximum(pa.max(axis=0), pb.max(axis=0))
    return lo, hi, np.add.reduceat(seg_e, idx)


def _heights(lz, lo, hi, bounds) -> np.ndarray:
    heights = _layer_thickness(lz, lo, hi, bounds)
    good = heights[heights > 0.01]
    fallback_h = float(np.median(good)) if good.size else 0.2
    heights = np.where(heights > 0.01, heights, fallback_h)
    if len(heights) and lz[0] > 0:
        heights[0] = min(lz[0], 2.0) if lz[0] > 0.01 else fallback_h
    return heights


def _line_ranges(tags, detection, seg_line, bounds, n_lines):
    """First and stop source line of each layer, (L,) int64 each."""
    nl = len(bounds) - 1
    first = bounds[:-1]
    if detection.startswith("tags") and nl:
        tl = tags.layer_lines
        j = np.searchsorted(tl, seg_line[first], side="right") - 1
        starts = np.where(j >= 0, tl[np.maximum(j, 0)], seg_line[first])
    else:
        starts = np.concatenate([[1], seg_line[first[1:] - 1] + 1]) if nl else np.zeros(0, np.int64)
    starts = np.asarray(starts, np.int64)
    if nl:
        starts[0] = 1
        starts = np.maximum.accumulate(starts)
    stops = np.append(starts[1:], n_lines + 1) if nl else starts
    return starts, stops


def _layers(lz, heights, bounds, starts, stops, lo, hi, ext, n_trav) -> tuple[Layer, ...]:
    # columns to Python numbers in bulk (tolist), then one record per layer
    cols = (lz.tolist(), heights.tolist(), bounds[:-1].tolist(), bounds[1:].tolist(), starts.tolist(),
            stops.tolist(), np.column_stack([lo, hi]).tolist(), ext.tolist(), n_trav.tolist())
    return tuple(
        Layer(k, z, h, a, b, ls, le, tuple(box), e, nt)
        for k, (z, h, a, b, ls, le, box, e, nt) in enumerate(zip(*cols, strict=True))
    )


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
        A ``.gcode``/``.bgcode``/``.gx`` file or its bytes.
    filament_diameter : float, optional
        Filament diameter in mm; default from the file header, else 2.85 for
        UltiGCode and 1.75 otherwise. Converts volumetric E to lengths.
    progress : callable(done_bytes, total_bytes), optional
        Called as parsing advances.

    Returns
    -------
    Toolpath
        Segments in bed mm; ``detection`` says how layers were found;
        ``statements`` what the file says about itself.

    Raises
    ------
    GcodeError
        Empty, binary, damaged or unreadable input (message names the file and the fix).
    """
    data, name = load_bytes(source)
    total = len(data)
    if progress:
        progress(0, total)
    statements = read_statements(data)
    diameter = _filament_diameter(filament_diameter, statements)
    ko = kernel_outputs(data, e_area=volumetric_area(statements, diameter))
    st, fst = ko.stats, ko.fstats
    if progress:
        progress(int(total * 0.9), total)
    short = Path(name).name
    warnings = _kernel_warnings(data, short, st)
    seg_a, seg_b, seg_z, seg_e, seg_line = ko.start, ko.end, ko.z, ko.e, ko.line
    tags = decode_tags(data, ko.cmt)
    m = _LH.search(data[:8192]) or _LH.search(data[-65536:])
    lh_hint = _finite(m.group(1)) if m else None
    bounds, lz, detection, w2 = assign_layers(seg_z, seg_line, tags.layer_lines, tags.layer_z, tags.style,
                                              lh_hint, seg_b)
    warnings += w2
    if seg_z.shape[0] == 0:
        warnings.append(f"{short}: no extruding moves found (not a 3D-printer file, or E is never used)")
    feature = _features(tags, seg_line, seg_z, detection, bounds)
    lo = hi = ext = None
    if len(lz):
        lo, hi, ext = _layer_boxes(seg_a, seg_b, seg_e, feature, bounds)
    heights = _heights(lz, lo, hi, bounds)
    starts, stops = _line_ranges(tags, detection, seg_line, bounds, int(st[K.ST_LINES]))
    n_trav = np.searchsorted(ko.travel_line, stops) - np.searchsorted(ko.travel_line, starts)
    generator = detect_generator(data[:65536])
    tp = Toolpath(
        start=seg_a, end=seg_b, z=seg_z, e=seg_e,
        width=_bead_width(seg_a, seg_b, seg_e, np.repeat(heights.astype(np.float32), np.diff(bounds)), diameter),
        feature=feature, tool=ko.tool, line=seg_line,
        layers=_layers(lz, heights, bounds, starts, stops, lo, hi, ext, n_trav) if len(lz) else (),
        detection=detection, filament_diameter=diameter, source=name, slicer=generator.name,
        warnings=warnings, generator=generator, statements=statements,
        filament_commanded_mm=float(fst[K.FS_XY_CMD]), filament_fed_mm=float(fst[K.FS_FED_HIGH]),
        volumetric=bool(st[K.ST_VOLUMETRIC]) or volumetric_area(statements, diameter) > 0,
    )
    if progress:
        progress(total, total)
    return tp
