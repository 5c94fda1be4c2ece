"""The objects of a multi-object plate: which G-code lines print which object, and where it lies on the bed.

A slicer labels the objects of a plate in one or more of these ways (all
"all at once" prints; the shared test files in ``PROVENANCE.md`` hold each):

* Klipper's ``EXCLUDE_OBJECT_DEFINE NAME=..`` / ``EXCLUDE_OBJECT_START NAME=..`` /
  ``EXCLUDE_OBJECT_END`` (PrusaSlicer/Orca "label objects: firmware-specific", or
  Moonraker's object processing);
* Marlin/Prusa ``M486 S<id>`` ... ``M486 S-1`` (names from ``M486 A<name>``);
* comments: PrusaSlicer/Slic3r/SuperSlicer/Orca ``; printing object <name> id:N copy M`` /
  ``; stop printing object``, Orca/Bambu ``; start printing object, unique label id: N``,
  Cura ``;MESH:<name>`` (``NONMESH`` and ``;LAYER:`` end it), ideaMaker ``;PRINTING: <name>``
  (``NON-OBJECT`` ends it).

The firmware can skip an object only where the file carries its own labels:
``EXCLUDE_OBJECT_*`` for Klipper (``EXCLUDE_OBJECT NAME=<name>``) and ``M486 S`` for
Marlin/Prusa firmware (``M486 P<id>``); comment labels still locate a failure.
:func:`read_objects` picks the most actionable style present and labels every
extruding segment of a :class:`~layerwatch.gcode.toolpath.Toolpath`;
:meth:`ObjectMap.locate` maps failing regions (bed mm) to objects.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from layerwatch.gcode.reader import load_bytes
from layerwatch.gcode.toolpath import Layer, Toolpath, part_mask

__all__ = ["ObjectMap", "Located", "PrintObject", "quiet_layers", "read_objects", "without_objects"]

#: (style, start regex (group 1 = name or id), end regex); first style present wins (firmware labels first)
_STYLES: tuple[tuple[str, re.Pattern, re.Pattern], ...] = (
    ("exclude_object", re.compile(rb"^EXCLUDE_OBJECT_START\s+NAME=['\"]?([^\s'\"]+)", re.M | re.I),
     re.compile(rb"^EXCLUDE_OBJECT_END\b", re.M | re.I)),
    ("m486", re.compile(rb"^M486\s+S(\d+)\s*(?:;.*)?$", re.M), re.compile(rb"^M486\s+S-1\b", re.M)),
    ("orca", re.compile(rb"^;\s*start printing object, unique label id:\s*(\d+)", re.M),
     re.compile(rb"^;\s*stop printing object, unique label id:", re.M)),
    ("slic3r", re.compile(rb"^;\s*printing object\s+(.+?)\s*$", re.M),
     re.compile(rb"^;\s*stop printing object\b", re.M)),
    ("cura", re.compile(rb"^;MESH:(?!NONMESH)(.+?)\s*$", re.M), re.compile(rb"^;(?:MESH:NONMESH|LAYER:)", re.M)),
    ("ideamaker", re.compile(rb"^;PRINTING:[ \t]*(?![ \t]|NON-OBJECT)(.+?)\s*$", re.M),
     re.compile(rb"^;PRINTING:\s*NON-OBJECT", re.M)),
)
_M486_NAME = re.compile(rb"^M486\s+A(.+?)\s*$", re.M)
_SAMPLE_MM = 0.5  # spacing of the points sampled along segments for the object raster, mm


@dataclass(frozen=True)
class PrintObject:
    """One labelled object of the plate.

    Attributes
    ----------
    index : int
        Position in :attr:`ObjectMap.objects` (the value in ``segment_object``).
    name : str
        The label as the file gives it (``"cube_1 id:0 copy 1"``, ``"B"``, ``"3"``).
    firmware_id : int or None
        The ``M486 S<id>`` of the file (Marlin/Prusa), None without M486 labels.
    klipper_name : str or None
        The ``EXCLUDE_OBJECT_START NAME`` of the file, upper case as Klipper keeps it; None without.
    bbox_mm : tuple of float
        ``(x0, y0, x1, y1)`` of its part segments (skirt and brim left out), bed mm.
    """

    index: int
    name: str
    firmware_id: int | None
    klipper_name: str | None
    bbox_mm: tuple[float, float, float, float]

    @property
    def center_mm(self) -> tuple[float, float]:
        b = self.bbox_mm
        return ((b[0] + b[2]) / 2, (b[1] + b[3]) / 2)


@dataclass(frozen=True)
class Located:
    """Where failing regions lie among the objects.

    Attributes
    ----------
    objects : tuple of int
        Indices of the objects the regions touch, most touched first.
    reason : str
        Why no single object can be cancelled (``""`` when exactly one is touched).
    """

    objects: tuple[int, ...]
    reason: str = ""

    @property
    def single(self) -> int | None:
        """The one object touched, or None (spans several, touches none, no labels)."""
        return self.objects[0] if len(self.objects) == 1 and not self.reason else None


@dataclass
class ObjectMap:
    """The labelled objects of a toolpath and the object of every extruding segment.

    Attributes
    ----------
    objects : tuple of PrintObject
    style : str
        Label style used (``"exclude_object"``, ``"m486"``, ``"orca"``, ``"slic3r"``, ``"cura"``,
        ``"ideamaker"``), ``""`` when the file labels no objects.
    segment_object : ndarray, shape (S,), int32
        Object index per toolpath segment, -1 outside every object (skirt, purge line, wipe tower).
    """

    objects: tuple[PrintObject, ...] = ()
    style: str = ""
    segment_object: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))

    @property
    def labelled(self) -> bool:
        """True when the file labels at least two objects (something to cancel one of)."""
        return len(self.objects) >= 2

    def by_name(self, name: str) -> PrintObject | None:
        return next((o for o in self.objects if name in (o.name, o.klipper_name)), None)

    def raster(self, toolpath: Toolpath, layer: int, cell_mm: float = 1.0) -> tuple[np.ndarray, tuple[float, float]]:
        """Object index per ``cell_mm`` bed cell printed up to ``layer`` (-1 none, -2 several), and its origin.

        Returns
        -------
        grid : ndarray, shape (H, W), int32
            Rows along +Y, columns along +X.
        origin : (x0, y0)
            Bed mm of the grid's corner.
        """
        stop = toolpath.layers[min(max(layer, 0), toolpath.n_layers - 1)].seg_stop
        obj = self.segment_object[:stop]
        keep = obj >= 0
        a, b, obj = toolpath.start[:stop][keep], toolpath.end[:stop][keep], obj[keep]
        n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / _SAMPLE_MM).astype(np.int64), 1) + 1
        seg = np.repeat(np.arange(len(a)), n)
        t = (np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n - 1, n)
        pts = a[seg] + (b[seg] - a[seg]) * t[:, None]
        if not len(pts):
            return np.full((1, 1), -1, np.int32), (0.0, 0.0)
        lo = np.floor(pts.min(axis=0)) - 1
        ij = np.floor((pts - lo) / cell_mm).astype(np.int64)
        shape = (int(ij[:, 1].max()) + 2, int(ij[:, 0].max()) + 2)
        grid = np.full(shape, -1, np.int32)
        first = np.full(shape, -1, np.int32)
        np.maximum.at(grid, (ij[:, 1], ij[:, 0]), obj[seg])
        first[:] = np.iinfo(np.int32).max
        np.minimum.at(first, (ij[:, 1], ij[:, 0]), obj[seg])
        grid[(grid >= 0) & (first != grid)] = -2  # two objects in one cell: touching it is ambiguous
        return grid, (float(lo[0]), float(lo[1]))

    def locate(self, toolpath: Toolpath, regions: Sequence, layer: int, *, cell_mm: float = 1.0) -> Located:
        """The objects printed (up to ``layer``) inside the failing regions' boxes.

        Parameters
        ----------
        toolpath : Toolpath
            The toolpath this map labels.
        regions : sequence of Region
            Failing regions (``bbox_mm`` in bed mm).
        layer : int
            Layer the regions were seen on.

        Returns
        -------
        Located
            One object, or the reason to pause instead (no labels, spans objects, touches none).
        """
        if not self.labelled:
            return Located((), "the G-code labels no objects (slice with label objects on)")
        if not regions:
            return Located((), "the failure has no region to place on an object")
        grid, (x0, y0) = self.raster(toolpath, layer, cell_mm)
        counts: dict[int, int] = {}
        for r in regions:
            bx0, by0, bx1, by1 = r.bbox_mm
            i0, i1 = max(int(np.floor((by0 - y0) / cell_mm)), 0), max(int(np.floor((by1 - y0) / cell_mm)) + 1, 0)
            j0, j1 = max(int(np.floor((bx0 - x0) / cell_mm)), 0), max(int(np.floor((bx1 - x0) / cell_mm)) + 1, 0)
            window = grid[i0:i1, j0:j1]
            if (window == -2).any():
                return Located((), "the failure lies where two objects touch")
            for k, c in zip(*np.unique(window[window >= 0], return_counts=True), strict=True):
                counts[int(k)] = counts.get(int(k), 0) + int(c)
        touched = tuple(sorted(counts, key=lambda k: -counts[k]))
        if not touched:
            return Located((), "the failure touches no object (beside the parts)")
        if len(touched) > 1:
            names = ", ".join(self.objects[k].name for k in touched)
            return Located(touched, f"the failure spans {len(touched)} objects ({names})")
        return Located(touched)


def _line_of(data: bytes) -> np.ndarray:
    """Byte offsets of the line starts of ``data`` (line ``k`` (1-based) starts at ``[k - 1]``)."""
    nl = np.frombuffer(data, np.uint8) == 10
    return np.concatenate([[0], np.flatnonzero(nl) + 1])


def _events(data: bytes, starts: np.ndarray, start: re.Pattern, end: re.Pattern) -> list[tuple[int, bytes | None]]:
    """``(line, key or None)`` of every start / end marker, in line order."""
    ev = [(int(np.searchsorted(starts, m.start(), "right")), m.group(1).strip()) for m in start.finditer(data)]
    ev += [(int(np.searchsorted(starts, m.start(), "right")), None) for m in end.finditer(data)]
    return sorted(ev, key=lambda e: e[0])


def _names_m486(data: bytes, starts: np.ndarray, events: list) -> dict[bytes, str]:
    """Names per ``M486 S<id>``: its ``M486 A<name>`` (the A line follows the S line), else the
    ``; printing object <name>`` comment within 3 lines of it (PrusaSlicer writes both)."""
    names: dict[bytes, str] = {}
    s_lines = [(line, key) for line, key in events if key is not None]
    for m in _M486_NAME.finditer(data):
        line = int(np.searchsorted(starts, m.start(), "right"))
        before = [key for ln, key in s_lines if ln < line]
        if before:
            names.setdefault(before[-1], m.group(1).decode("utf-8", "replace").strip())
    _, start, end = next(st for st in _STYLES if st[0] == "slic3r")
    comments = [(ln, key) for ln, key in _events(data, starts, start, end) if key is not None]
    for line, key in s_lines:
        near = [c for ln, c in comments if abs(ln - line) <= 3]
        if near and key not in names:
            names[key] = near[0].decode("utf-8", "replace")
    return names


def read_objects(source: str | Path | bytes, toolpath: Toolpath, style: str | None = None) -> ObjectMap:
    """Label the segments of ``toolpath`` (read from ``source``) with the plate's objects.

    Parameters
    ----------
    source : str, Path or bytes
        The G-code the toolpath was read from (``.bgcode`` is decoded).
    toolpath : Toolpath
        Its :func:`~layerwatch.gcode.reader.read_toolpath` result (``line`` per segment).
    style : str, optional
        Read this label style only (default: the first one present, firmware labels first).

    Returns
    -------
    ObjectMap
        Empty (``style == ""``) when the file labels no objects.
    """
    data, _ = load_bytes(source)
    starts = _line_of(data)
    for name, start, end in [st for st in _STYLES if style in (None, st[0])]:
        events = _events(data, starts, start, end)
        if any(key is not None for _, key in events):
            style = name
            break
    else:
        return ObjectMap(segment_object=np.full(toolpath.n_segments, -1, np.int32))
    keys: list[bytes] = []
    for _, key in events:
        if key is not None and key not in keys:
            keys.append(key)
    ev_lines = np.array([line for line, _ in events], np.int64)
    ev_obj = np.array([-1 if key is None else keys.index(key) for _, key in events], np.int32)
    k = np.searchsorted(ev_lines, toolpath.line, "left") - 1  # the last marker before each segment's line
    seg_obj = np.where(k >= 0, ev_obj[np.maximum(k, 0)], -1).astype(np.int32)
    seg_obj[~part_mask(toolpath.feature)] = -1
    a486 = _names_m486(data, starts, events) if style == "m486" else {}
    objects: list[PrintObject] = []
    relabel = np.full(len(keys) + 1, -1, np.int32)  # objects without extrusion are left out
    for i, key in enumerate(keys):
        mine = seg_obj == i
        if not mine.any():
            continue
        pts = np.concatenate([toolpath.start[mine], toolpath.end[mine]])
        text = key.decode("utf-8", "replace")
        relabel[i] = len(objects)
        objects.append(PrintObject(
            index=len(objects), name=a486.get(key, text), firmware_id=int(text) if style == "m486" else None,
            klipper_name=text.upper() if style == "exclude_object" else None,
            bbox_mm=(*map(float, pts.min(axis=0)), *map(float, pts.max(axis=0)))))  # type: ignore[arg-type]
    return ObjectMap(tuple(objects), style, relabel[seg_obj])


def without_objects(toolpath: Toolpath, objects: ObjectMap, cancelled: Mapping[int, int]) -> Toolpath:
    """``toolpath`` without what cancelled objects no longer print.

    Parameters
    ----------
    toolpath : Toolpath
        The full toolpath ``objects`` labels.
    objects : ObjectMap
    cancelled : mapping of int to int
        Object index -> the last layer it printed (it was cancelled after that layer); its
        segments on later layers are dropped, those up to it stay (that part is on the bed).

    Returns
    -------
    Toolpath
        Same layers (indices, heights, line ranges) with fewer segments.
    """
    drop = np.zeros(toolpath.n_segments, bool)
    for index, after in cancelled.items():
        if after + 1 < toolpath.n_layers:
            first = toolpath.layers[max(after + 1, 0)].seg_start
            drop[first:] |= objects.segment_object[first:] == index
    keep = ~drop
    new_index = np.concatenate([[0], np.cumsum(keep)])
    layers: list[Layer] = [replace(lay, seg_start=int(new_index[lay.seg_start]), seg_stop=int(new_index[lay.seg_stop]))
                           for lay in toolpath.layers]
    arrays = {name: getattr(toolpath, name)[keep] for name in ("start", "end", "z", "e", "width", "feature", "tool", "line")}
    return replace(toolpath, layers=tuple(layers), **arrays)


def quiet_layers(toolpath: Toolpath, objects: ObjectMap | None = None) -> frozenset[int]:
    """Layers that print none of the part: only the start or end G-code's purge lines, wipes or primes.

    A layer is quiet when none of its segments belongs to a labelled object (files that label
    objects: the start and end scripts never do) or, without labels, when all of them are
    skirt, purge, brim or wipe tower. The monitor does not judge those layers.
    """
    labelled = objects is not None and objects.style != "" and len(objects.objects) > 0
    part = objects.segment_object >= 0 if labelled else part_mask(toolpath.feature)  # type: ignore[union-attr]
    return frozenset(lay.index for lay in toolpath.layers
                     if lay.n_segments and not part[lay.seg_start:lay.seg_stop].any())
