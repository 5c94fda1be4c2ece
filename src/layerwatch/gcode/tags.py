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


#: bytes of a comment that key the classification cache; longer comments are classified one by one
KEY_BYTES = 48
_MAX_TAG_BYTES = 200  # a comment is read up to its newline or this many bytes


def _comment_keys(data: bytes, offs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first :data:`KEY_BYTES` bytes of each comment (zero after its newline), its length up to
    the newline, and whether it is longer than the key: ``(C, KEY_BYTES)`` uint8, ``(C,)`` int64, ``(C,)`` bool."""
    n, w = len(data), KEY_BYTES
    buf = np.frombuffer(data, np.uint8)
    inside = offs <= n - w
    if n >= w:
        keys = np.lib.stride_tricks.sliding_window_view(buf, w)[np.minimum(offs, n - w)]
    else:
        keys = np.zeros((offs.shape[0], w), np.uint8)
    for r in np.flatnonzero(~inside).tolist():  # the last few comments of the file
        tail = buf[offs[r] : offs[r] + w]
        keys[r] = 0
        keys[r, : tail.shape[0]] = tail
    is_nl = keys == 10
    lengths = np.argmax(is_nl, axis=1)
    ended = is_nl[np.arange(keys.shape[0]), lengths]
    lengths[~ended] = w
    keys *= np.arange(w) < lengths[:, None]  # zero from the newline on
    long = ~ended & inside
    return keys, lengths.astype(np.int64), long


def _row_hash(keys: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """A 64-bit multiplicative hash of each key row and its length, (C,) uint64."""
    words = keys.view(np.uint64)
    h = lengths.astype(np.uint64)
    for j in range(words.shape[1]):
        h = h * np.uint64(0x9E3779B97F4A7C15) + words[:, j]
    return h


def _distinct_comments(data: bytes, offs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group equal comments: ``(first, inverse, long)`` where comment ``i`` equals comment
    ``first[inverse[i]]`` (exactly: keys are compared, not only hashed); ``long`` comments
    (beyond the key) are each their own group."""
    keys, lengths, long = _comment_keys(data, offs)
    h = _row_hash(keys, lengths)
    h[long] = np.uint64(0)
    _, first, inverse = np.unique(h, return_index=True, return_inverse=True)
    rep = first[inverse][~long]
    short = ~long
    if not (np.array_equal(keys[rep], keys[short]) and np.array_equal(lengths[rep], lengths[short])):  # a collision
        _, first, inverse = np.unique(np.column_stack([keys, lengths.view(np.uint8).reshape(-1, 8)]),
                                      axis=0, return_index=True, return_inverse=True)
    return first, inverse.reshape(-1), long


def _raw(data: bytes, off: int) -> bytes:
    end = data.find(b"\n", off, off + _MAX_TAG_BYTES)
    return data[off : end if end >= 0 else off + _MAX_TAG_BYTES]


def _classify_rows(data: bytes, offs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per comment: layer style index (-1 none), tag z (NaN), feature code (-1), ``;Z:`` value
    (NaN none) and Cura label id (-1 none), each (C,); each distinct comment classified once."""
    first, inverse, long = _distinct_comments(data, offs)
    names = [s[0] for s in LAYER_STYLES]
    labels: dict[bytes, int] = {}

    def classify(off: int) -> tuple[int, float, int, float, int]:
        style, z, code, zval = _classify(_raw(data, off).rstrip(b"\r"))
        if style == "cura":
            return names.index(style), z, code, float("nan"), labels.setdefault(zval or b"", len(labels))
        zv = float(zval) if zval is not None and style is None else float("nan")
        return (-1 if style is None else names.index(style)), z, code, zv, -1

    uniq = [classify(off) for off in offs[first].tolist()]
    cols = [np.array(c)[inverse] for c in zip(*uniq, strict=True)] if uniq else [np.zeros(0)] * 5
    for r in np.flatnonzero(long).tolist():
        for col, v in zip(cols, classify(int(offs[r])), strict=True):
            col[r] = v
    style, z, code, zval, label = cols
    return style.astype(np.int64), z.astype(np.float64), code.astype(np.int64), zval.astype(np.float64), label.astype(np.int64)


def decode_tags(data: bytes, cmt: np.ndarray) -> TagScan:
    """Decode candidate comments ``cmt`` (``(C, 2)`` int64: byte offset, line) of ``data``.

    Vectorised: equal comments (most of them: ``;TYPE:WALL-OUTER`` ...) are classified once
    by regular expression, the rest is NumPy over all comments.
    """
    if len(cmt) == 0:
        return TagScan()
    offs, lines = np.ascontiguousarray(cmt[:, 0]), np.ascontiguousarray(cmt[:, 1])
    style, tz, code, zval, label = _classify_rows(data, offs)
    cura = names_index("cura")
    rows = np.flatnonzero(style == cura)  # ideaMaker repeats ;LAYER:n per object: keep the first
    repeat = np.zeros(style.shape[0], bool)
    repeat[rows[1:][label[rows[1:]] == label[rows[:-1]]]] = True
    style[repeat] = -2
    zc = names_index("z-comment")
    zrows = (style == zc) | ((style == -1) & ~np.isnan(zval))
    zl, zv = lines[zrows], np.where(style[zrows] == zc, tz[zrows], zval[zrows])
    feat = (style == -1) & np.isnan(zval) & (code >= 0)
    scan = TagScan(feature_lines=lines[feat], feature_codes=code[feat].astype(np.uint8))
    for k, (name, _rx, _zg) in enumerate(LAYER_STYLES):
        hit = style == k
        count = int(np.count_nonzero(hit))
        if count >= 2 or (count and name != "z-comment"):
            scan.style = name
            scan.layer_lines = lines[hit]
            z = tz[hit]
            if np.isnan(z).any() and zl.size:
                # a ;Z: (or ; Z_HEIGHT:) shortly after the layer tag gives its height
                nxt = np.append(scan.layer_lines[1:], np.iinfo(np.int64).max)
                j = np.searchsorted(zl, scan.layer_lines, side="left")
                ok = (j < len(zl)) & (zl[np.minimum(j, len(zl) - 1)] < nxt)
                z[ok & np.isnan(z)] = zv[np.minimum(j, len(zl) - 1)][ok & np.isnan(z)]
            scan.layer_z = z
            break
    return scan


def names_index(name: str) -> int:
    """Index of a layer style in :data:`LAYER_STYLES`."""
    return [s[0] for s in LAYER_STYLES].index(name)
