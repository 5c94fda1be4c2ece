"""What a G-code file says about itself: the slicer's own statements.

Slicers write summaries into their output: layer count, filament used (mm,
cm³, g), the first layer's bounding box (``M555`` for Prusa firmware, the
``G29 A1 X Y I J`` bed-levelling area of Bambu/Orca start G-code), the bed
shape, the print's height. :func:`read_statements` reads them (from the head
and tail of the text; a ``.bgcode``'s metadata blocks arrive there as
comments) so that the reader's own result can be checked against them
(:func:`compare`). Nothing here is computed from the moves.

Known quirks, kept as the files have them (the reader is not bent to them):

- Bambu Studio 2.x writes ``; total filament volume [cm^3] : 636.81`` for
  0.64 cm³: the number is mm³. :func:`read_statements` records the value as
  written in ``filament_volume_stated`` and converts it when it is 1000x the
  volume of the stated length (``volume_note`` says so).
- Slic3r 1.2 writes ``; filament used = 1482.1mm, 34.4mm (3.6cm3)``: the first
  number is the length (3.6 cm³ / 2.405 mm² = 1497 mm); the second is not
  documented and is not used.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

__all__ = ["Statements", "read_statements", "compare", "Disagreement"]

_N = rb"([-+]?(?:\d+\.?\d*|\.\d+))"


def _num(raw: bytes | None) -> float | None:
    """A finite float from ``raw``, or None (malformed header numbers are ignored, never raised)."""
    if raw is None:
        return None
    try:
        v = float(raw)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def _nums(raw: bytes) -> list[float]:
    return [v for v in (_num(t) for t in re.findall(_N, raw)) if v is not None]


_LAYERS = re.compile(
    rb"(?im)^;\s*(?:total layer number:|LAYER_COUNT:|layer_count:|total_layer_count\s*=)\s*(\d+)\s*$"
)
#: filament length statements: (regex, factor to mm); a list of per-extruder values is summed
_LENGTH = (
    (re.compile(rb"(?im)^;\s*filament used \[mm\]\s*=\s*([\d., ]+?)\s*$"), 1.0),
    (re.compile(rb"(?im)^;\s*total filament length \[mm\]\s*:\s*([\d., ]+?)\s*$"), 1.0),
    (re.compile(rb"(?im)^;\s*Filament used:\s*([\d.m, ]+?)\s*$"), 1000.0),  # Cura: metres, 'm' suffixes
    (re.compile(rb"(?im)^;\s*Filament length:\s*([\d.]+)\s*mm"), 1.0),  # Simplify3D
    (re.compile(rb"(?im)^;\s*filament used\s*=\s*([\d.]+)\s*mm"), 1.0),  # Slic3r 1.2 (first value)
    (re.compile(rb"(?im)^;\s*filament_length_m\s*=\s*([\d.]+)"), 1000.0),  # Slic3r 1.3
    (re.compile(rb"(?im)^;\s*---\s*filament used:\s*([\d.]+)\s*mm"), 1.0),  # Kiri:Moto
    (re.compile(rb"(?im)^;\s*Ext #?\d+\s*=\s*([\d.]+)\s*mm"), 1.0),  # KISSlicer (first extruder)
    (re.compile(rb"(?im)^;\s*Material#1 Used:\s*([\d.]+)\s*$"), 1.0),  # ideaMaker, extruder 1
)
_VOLUME = (
    re.compile(rb"(?im)^;\s*filament used \[cm3\]\s*=\s*([\d., ]+?)\s*$"),
    re.compile(rb"(?im)^;\s*total filament volume \[cm\^3\]\s*:\s*([\d., ]+?)\s*$"),
    re.compile(rb"(?im)^;\s*filament_volume_cm3\s*=\s*([\d.]+)"),
    re.compile(rb"(?im)^;\s*filament used\s*=[^\n(]*\(([\d.]+)cm3\)"),
    re.compile(rb"(?im)^;\s*Ext #?\d+\s*=\s*[\d.]+\s*mm\s*\(([\d.]+)\s*cm\^3\)"),
)
#: Cura UltiGCode header: ';MATERIAL:18720' is mm^3 of filament (extruder 1; MATERIAL2 the second)
_ULTI_MATERIAL = re.compile(rb"(?m)^;MATERIAL2?:(\d+)\s*$")
_MASS = (
    re.compile(rb"(?im)^;\s*total filament used \[g\]\s*=\s*([\d.]+)"),
    re.compile(rb"(?im)^;\s*filament used \[g\]\s*=\s*([\d., ]+?)\s*$"),
    re.compile(rb"(?im)^;\s*total filament weight \[g\]\s*:\s*([\d.]+)"),
)
_M555 = re.compile(rb"(?m)^\s*M555\s+X" + _N + rb"\s+Y" + _N + rb"\s+W" + _N + rb"\s+H" + _N)
_G29_AREA = re.compile(rb"(?m)^\s*G29 A1? X" + _N + rb" Y" + _N + rb" I" + _N + rb" J" + _N)
_CURA_BOX = {k: re.compile(rb"(?m)^;" + k.encode() + rb":" + _N + rb"\s*$") for k in ("MINX", "MINY", "MAXX", "MAXY")}
_BED_POLY = re.compile(rb"(?im)^;\s*(?:bed_shape|printable_area)\s*=\s*([\dx.,\- ]+?)\s*$")
_BED_XY = re.compile(rb"(?im)^;\s*bed_size_([xy])_mm\s*[=:]\s*" + _N)
_MAXZ = re.compile(rb"(?im)^;\s*(?:max_z_height:|MAXZ:)\s*" + _N)
_DIAM = re.compile(
    rb"(?im)^;\s*(?:filament_diameter0?|filament_diameter_mm_0|Filament Diameter #1)\s*[=:]\s*" + _N
)
_CURA_DIAM = re.compile(rb"material_diameter\s*=\s*" + _N)
_FIRST_H = re.compile(
    # not KISSlicer's first_layer_thickness_mm: a per-style setting (negative = percent) that its
    # per-object layering overrides (layer 0 printed at 0.263 / 0.278 mm where it says 0.2)
    rb"(?i)(?:first_layer_height|initial_layer_print_height|layer_height_0|z_layer_height_first_layer_mm)\s*[=:,]\s*" + _N + rb"(?![\d%])"
)
_FLAVOR = re.compile(rb"(?im)^;\s*(?:FLAVOR:|gcode_flavor\s*=\s*)(\S+)")
_LAYER_H = re.compile(rb"(?im)^;\s*(?:layer_height\s*[=:]|Layer height:)\s*" + _N)


@dataclass
class Statements:
    """A file's statements about itself; ``None`` where the file states nothing.

    Attributes
    ----------
    layer_count : int or None
    filament_mm : float or None
        Filament length the slicer computed (all extruders), mm.
    filament_cm3 : float or None
        Filament volume, cm³ (after the Bambu mm³ correction, see the module notes).
    filament_volume_stated : float or None
        The volume number exactly as written.
    filament_g : float or None
        Filament mass, g.
    first_layer_box : tuple (xmin, ymin, xmax, ymax) or None
        The first layer's extent as the slicer told the firmware, mm.
    first_layer_box_source : str
        The statement it came from (``"M555"``, ``"G29 A1"``).
    print_box : tuple (xmin, ymin, xmax, ymax) or None
        The whole print's XY extent (Cura ``;MINX`` ...), mm.
    bed_polygon : list of (x, y) or None
        The printable area, mm.
    max_z : float or None
        Height of the top layer, mm.
    filament_diameter : float or None
        mm.
    layer_height : float or None
        mm.
    first_layer_height : float or None
        The first layer's Z (its thickness over the bed), mm.
    flavor : str or None
        G-code flavour (``"UltiGCode"``, ``"RepRap"``, ``"marlin2"``).
    notes : list of str
        How odd statements were read.
    """

    layer_count: int | None = None
    filament_mm: float | None = None
    filament_cm3: float | None = None
    filament_volume_stated: float | None = None
    filament_g: float | None = None
    first_layer_box: tuple[float, float, float, float] | None = None
    first_layer_box_source: str = ""
    print_box: tuple[float, float, float, float] | None = None
    bed_polygon: list[tuple[float, float]] | None = None
    max_z: float | None = None
    filament_diameter: float | None = None
    layer_height: float | None = None
    first_layer_height: float | None = None
    flavor: str | None = None
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        """JSON-ready dict (tuples as lists)."""
        out = dict(self.__dict__)
        for k in ("first_layer_box", "print_box"):
            if out[k] is not None:
                out[k] = list(out[k])
        if out["bed_polygon"] is not None:
            out["bed_polygon"] = [list(p) for p in out["bed_polygon"]]
        out["notes"] = list(self.notes)
        return out


def _first_total(rx_list, text: bytes, factor: float = 1.0) -> float | None:
    for rx in rx_list:
        m = rx.search(text)
        if m:
            vals = _nums(m.group(1))
            if vals:
                return sum(vals) * factor
    return None


def _length(text: bytes) -> float | None:
    for rx, factor in _LENGTH:
        m = rx.search(text)
        if m:
            vals = _nums(m.group(1))
            if vals:
                return sum(vals) * factor
    return None


def _boxes(st: Statements, text: bytes) -> None:
    m = _M555.search(text)
    if m:
        x, y, w, h = (_num(g) for g in m.groups())
        if None not in (x, y, w, h):
            st.first_layer_box, st.first_layer_box_source = (x, y, x + w, y + h), "M555"
    m = _G29_AREA.search(text) if st.first_layer_box is None else None
    if m:
        x, y, w, h = (_num(g) for g in m.groups())
        if None not in (x, y, w, h):
            st.first_layer_box, st.first_layer_box_source = (x, y, x + w, y + h), "G29 A1"
    cura = [_CURA_BOX[k].search(text) for k in ("MINX", "MINY", "MAXX", "MAXY")]
    if all(cura):
        vals = [_num(c.group(1)) for c in cura]
        if None not in vals:
            st.print_box = tuple(vals)


def _bed(st: Statements, text: bytes) -> None:
    m = _BED_POLY.search(text)
    if m:
        pts = []
        for pair in m.group(1).split(b","):
            xy = pair.strip().split(b"x")
            if len(xy) == 2 and _num(xy[0]) is not None and _num(xy[1]) is not None:
                pts.append((_num(xy[0]), _num(xy[1])))
        st.bed_polygon = pts or None
        return
    sizes = {m.group(1).lower(): _num(m.group(2)) for m in _BED_XY.finditer(text)}
    if sizes.get(b"x") and sizes.get(b"y"):
        x, y = sizes[b"x"], sizes[b"y"]
        st.bed_polygon = [(0.0, 0.0), (x, 0.0), (x, y), (0.0, y)]


_THUMBNAIL = re.compile(rb"(?is);\s*thumbnail\w* begin.*?;\s*thumbnail\w* end|; THUMBNAIL_BLOCK_START.*?; THUMBNAIL_BLOCK_END")
_KEEP = re.compile(rb"(?m)^[ \t]*(?:;|\(|M555 |G29 A)[^\n]*")


def _statement_lines(data: bytes, head_bytes: int, tail_bytes: int) -> bytes:
    """The comment lines (and M555 / G29 A lines) of the head and tail, thumbnails removed:
    a few hundred kB at most, so that the ~30 statement patterns scan little."""
    parts = [data] if len(data) <= head_bytes + tail_bytes else [data[:head_bytes], data[-tail_bytes:]]
    out = []
    for part in parts:
        part = _THUMBNAIL.sub(b"", part)
        out.extend(_KEEP.findall(part))
    return b"\n".join(out) + b"\n"


def read_statements(data: bytes, head_bytes: int = 1 << 19, tail_bytes: int = 1 << 18) -> Statements:
    """Read the statements from the head and tail of G-code ``data``.

    Parameters
    ----------
    data : bytes
        G-code text (a ``.bgcode`` already decoded).
    head_bytes, tail_bytes : int
        How much of the start and end to search (PrusaSlicer writes its
        summary at the end, Bambu/Cura at the start).

    Returns
    -------
    Statements
    """
    text = _statement_lines(data, head_bytes, tail_bytes)
    st = Statements()
    m = _LAYERS.search(text)
    st.layer_count = int(m.group(1)) if m else None
    st.filament_mm = _length(text)
    st.filament_g = _first_total(_MASS, text)
    m = _DIAM.search(text) or _CURA_DIAM.search(text)
    d = _num(m.group(1)) if m else None
    st.filament_diameter = d if d is not None and 0.5 <= d <= 5.0 else None
    vol = _first_total(_VOLUME, text)
    ulti = [v for v in (_num(m.group(1)) for m in _ULTI_MATERIAL.finditer(text)) if v is not None]
    if vol is None and ulti:
        vol = sum(ulti) / 1000.0
        st.notes.append(f"UltiGCode header ;MATERIAL: {sum(ulti):g} mm^3 read as {vol:g} cm^3")
    st.filament_volume_stated = vol
    st.filament_cm3 = vol
    if vol and st.filament_mm and st.filament_diameter:
        expect = st.filament_mm * math.pi * st.filament_diameter**2 / 4 / 1000.0
        if expect > 0 and 500 < vol / expect < 2000:
            st.filament_cm3 = vol / 1000.0
            st.notes.append(f"stated volume {vol:g} 'cm^3' is mm^3 (Bambu Studio writes mm^3 there); read as {vol / 1000:g} cm^3")
    _boxes(st, text)
    _bed(st, text)
    m = _MAXZ.search(text)
    st.max_z = _num(m.group(1)) if m else None
    m = _FLAVOR.search(text)
    st.flavor = m.group(1).decode("latin-1") if m else None
    m = _LAYER_H.search(text)
    st.layer_height = _num(m.group(1)) if m else None
    # the first positive value: KISSlicer writes percentages as negative numbers (-50 = 50 %)
    st.first_layer_height = next((v for m in _FIRST_H.finditer(text) if (v := _num(m.group(1))) and v > 0), None)
    return st


@dataclass(frozen=True)
class Disagreement:
    """One statement that the reading contradicts."""

    field: str
    stated: float
    read: float
    limit: str

    def __str__(self) -> str:
        return f"{self.field}: the file states {self.stated:g}, the reader finds {self.read:g} (beyond {self.limit})"


def compare(st: Statements, *, layers: int, filament_mm: float, max_z: float | None,
            first_layer_box: tuple[float, float, float, float] | None,
            first_layer_z: float | None = None, filament_cm3: float | None = None) -> list[Disagreement]:
    """Statements that the reading contradicts: layers beyond ±1, filament or max Z beyond 2 %,
    a first layer more than 0.05 mm off the stated height or reaching more than 2 mm outside
    the stated first-layer box."""
    out: list[Disagreement] = []
    if st.first_layer_height and first_layer_z is not None and abs(first_layer_z - st.first_layer_height) > 0.05:
        out.append(Disagreement("first layer Z (mm)", st.first_layer_height, round(first_layer_z, 3), "0.05 mm"))
    if st.layer_count is not None and abs(layers - st.layer_count) > 1:
        out.append(Disagreement("layers", st.layer_count, layers, "1 layer"))
    if st.filament_mm and abs(filament_mm - st.filament_mm) > 0.02 * st.filament_mm:
        out.append(Disagreement("filament (mm)", st.filament_mm, round(filament_mm, 2), "2 %"))
    # the stated max Z may include a final lift (Cura's MAXZ): the top layer may sit one layer below it
    lift = (st.layer_height or 0.0) + 0.05
    if st.filament_cm3 and filament_cm3 is not None and abs(filament_cm3 - st.filament_cm3) > max(
            0.02 * st.filament_cm3, 0.006):  # statements round to 0.01 cm^3
        out.append(Disagreement("filament (cm3)", st.filament_cm3, round(filament_cm3, 3), "2 %"))
    if st.max_z and max_z is not None and not (st.max_z - max(lift, 0.02 * st.max_z) <= max_z <= st.max_z + 0.05):
        out.append(Disagreement("max Z (mm)", st.max_z, round(max_z, 3), "2 %"))
    if st.first_layer_box and first_layer_box is not None:
        sx0, sy0, sx1, sy1 = st.first_layer_box
        x0, y0, x1, y1 = first_layer_box
        over = max(sx0 - x0, sy0 - y0, x1 - sx1, y1 - sy1)
        if over > 2.0:
            out.append(Disagreement(f"first layer outside the {st.first_layer_box_source} box (mm)", 0.0,
                                    round(over, 2), "2 mm"))
    return out
