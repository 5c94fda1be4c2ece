"""Slicer comment tags: layer changes and feature types.

The kernel hands over the byte offsets of ``;`` comments that may be tags;
this module decodes those few lines with regular expressions.

Layer tag styles, by slicer: PrusaSlicer/SuperSlicer/Orca ``;LAYER_CHANGE``
(+ ``;Z:``), Cura/ideaMaker ``;LAYER:n``, Simplify3D ``; layer N, Z = z``,
Bambu ``; CHANGE_LAYER`` (+ ``; Z_HEIGHT:``), KISSlicer ``; BEGIN_LAYER_OBJECT z=``,
FlashPrint ``;layer:<thickness>`` (Z from the moves), and a bare ``;Z:z`` as the last resort.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from layerwatch.gcode.toolpath import feature_code

__all__ = ["TagScan", "decode_tags", "feature_from_name"]

_NUM = r"([-+]?\d*\.?\d+)"
#: (style name, regex, group of z or None); order = priority when several styles are present
LAYER_STYLES: tuple[tuple[str, re.Pattern, int | None], ...] = (
    ("prusaslicer", re.compile(rb"^;LAYER_CHANGE\s*$"), None),
    ("bambu", re.compile(rb"^;\s*CHANGE_LAYER\s*$"), None),
    ("cura", re.compile(rb"^;LAYER:\s*(-?\d+)\s*$"), None),
    ("simplify3d", re.compile(rb"^;\s*layer\s+\d+,\s*Z\s*=\s*" + _NUM.encode()), 1),
    ("kisslicer", re.compile(rb"^;\s*BEGIN_LAYER_OBJECT\s+z=" + _NUM.encode()), 1),
    # FlashPrint's number is the layer's thickness, not its Z: Z comes from the moves
    ("flashprint", re.compile(rb"^;layer:" + _NUM.encode() + rb"\s*$"), None),
    ("z-comment", re.compile(rb"^;Z:" + _NUM.encode() + rb"\s*$"), 1),
)
_ZVAL = re.compile(rb"^;\s*(?:Z:|Z_HEIGHT:)\s*" + _NUM.encode())
_FEATURE = (
    re.compile(rb"^;TYPE:\s*(.+?)\s*$"),
    re.compile(rb"^;\s*FEATURE:\s*(.+?)\s*$"),
    re.compile(rb"^;\s*feature\s+(.+?)\s*$"),
    re.compile(rb"^;\s*'([A-Za-z /]+ Path)'"),
)


def feature_from_name(name: str) -> int:
    """Map a slicer's feature label to a code of :data:`~layerwatch.gcode.toolpath.FEATURES`."""
    s = name.lower().replace("-", " ").replace("_", " ")
    if "tower" in s:  # wipe tower, prime tower
        key = "wipe_tower"
    elif "purge" in s or "prime" in s or "flush" in s:
        key = "purge"
    elif "wipe" in s:
        key = "wipe"
    elif "brim" in s:
        key = "brim"
    elif "skirt" in s:
        key = "skirt"
    elif "support" in s:
        key = "support"
    elif "bridge" in s:
        key = "bridge"
    elif "external" in s or "outer" in s or s.strip() == "perimeter path":
        key = "external_perimeter"
    elif "perimeter" in s or "wall" in s or "loop" in s or "shell" in s:
        key = "perimeter"
    elif "top" in s or "ironing" in s:
        key = "top_solid_infill"
    elif "solid" in s or "skin" in s or "bottom" in s:
        key = "solid_infill"
    elif "infill" in s or "fill" in s or "sparse" in s:
        key = "infill"
    else:
        key = "other"
    return feature_code(key)


@dataclass
class TagScan:
    """Decoded tags: layer starts and feature changes, by source line."""

    style: str | None = None
    layer_lines: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    layer_z: np.ndarray = field(default_factory=lambda: np.zeros(0))
    feature_lines: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    feature_codes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))


def _classify(text: bytes) -> tuple[str | None, float, int, bytes | None]:
    """(layer style or None, tag z or NaN, feature code or -1, ``;Z:`` value bytes or None)."""
    style, z, code, zval = None, float("nan"), -1, None
    for name, rx, zg in LAYER_STYLES:
        m = rx.match(text)
        if m:
            style = name
            z = float(m.group(zg)) if zg else float("nan")
            if name == "cura":
                zval = m.group(1)  # the label, to drop ideaMaker's per-object repeats
            break
    if style is None or style == "z-comment":
        mz = _ZVAL.match(text)
        if mz and style is None:
            zval = mz.group(1)
    if style is None:
        for rx in _FEATURE:
            m = rx.match(text)
            if m:
                code = feature_from_name(m.group(1).decode("latin-1"))
                break
    return style, z, code, zval


def decode_tags(data: bytes, cmt: np.ndarray) -> TagScan:
    """Decode candidate comments ``cmt`` (``(C, 2)`` int64: byte offset, line) of ``data``."""
    per_style: dict[str, list[tuple[int, float]]] = {s[0]: [] for s in LAYER_STYLES}
    zvals: list[tuple[int, float]] = []
    flines: list[int] = []
    fcodes: list[int] = []
    last_cura: bytes | None = None
    cache: dict[bytes, tuple] = {}
    find = data.find
    # two flat lists (a nested tolist() builds a small list per comment); the raw line is the
    # cache key and only a cache miss strips its CR
    offs = cmt[:, 0].tolist() if len(cmt) else []
    lines = cmt[:, 1].tolist() if len(cmt) else []
    for off, line in zip(offs, lines, strict=True):
        end = find(b"\n", off, off + 200)
        raw = data[off : end if end >= 0 else off + 200]
        hit = cache.get(raw)
        if hit is None:
            hit = _classify(raw.rstrip(b"\r"))
            if len(cache) < 100000:
                cache[raw] = hit
        style, z, code, zval = hit
        if style is not None:
            if style == "cura":
                if zval == last_cura:
                    continue
                last_cura = zval
            elif style == "z-comment":
                zvals.append((line, z))
            per_style[style].append((line, z))
        elif zval is not None:
            zvals.append((line, float(zval)))
        elif code >= 0:
            flines.append(line)
            fcodes.append(code)
    scan = TagScan(
        feature_lines=np.asarray(flines, np.int64), feature_codes=np.asarray(fcodes, np.uint8)
    )
    for name, _rx, _zg in LAYER_STYLES:
        hits = per_style[name]
        if len(hits) >= 2 or (hits and name != "z-comment"):
            scan.style = name
            scan.layer_lines = np.array([h[0] for h in hits], np.int64)
            z = np.array([h[1] for h in hits], np.float64)
            if np.isnan(z).any() and zvals:
                # a ;Z: (or ; Z_HEIGHT:) shortly after the layer tag gives its height
                zl = np.array([v[0] for v in zvals], np.int64)
                zv = np.array([v[1] for v in zvals])
                nxt = np.append(scan.layer_lines[1:], np.iinfo(np.int64).max)
                k = np.searchsorted(zl, scan.layer_lines, side="left")
                ok = (k < len(zl)) & (zl[np.minimum(k, len(zl) - 1)] < nxt)
                z[ok & np.isnan(z)] = zv[np.minimum(k, len(zl) - 1)][ok & np.isnan(z)]
            scan.layer_z = z
            break
    return scan
