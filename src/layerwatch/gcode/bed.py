"""The bed a G-code file was sliced for, and a safe park spot on it.

Every move the snapshot block emits must stay on the printer's bed (``DESIGN.md``,
"Printer safety"). The bed comes, in this order, from an explicit ``--bed``
option, from what the slicer wrote into the file, or from the ``[printer]``
volume of the configuration:

==========================  ==================================================
slicer                      statement read
==========================  ==================================================
PrusaSlicer, SuperSlicer,   ``; bed_shape = 5x0,215x0,215x220,5x220`` (polygon),
Slic3r                      ``; max_print_height = 250``
OrcaSlicer, Bambu Studio    ``; printable_area = 0x0,256x0,256x256,0x256``,
                            ``; printable_height = 256``
Cura                        ``machine_width`` / ``machine_depth`` /
                            ``machine_height`` / ``machine_center_is_zero``
                            (``;SETTING_3`` footer or plain ``;key = value``)
KISSlicer, IceSL            ``bed_size_x_mm`` / ``bed_size_y_mm`` (/ ``bed_size_z_mm``)
Kiri:Moto                   ``; Bed left:0 right:300 top:300 bottom:0``
==========================  ==================================================

Coordinates are the file's own (bed mm, the G-code origin), the same frame as
the moves it contains.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from layerwatch.errors import ConfigError

__all__ = ["Bed", "bed_from_gcode", "parse_bed", "parse_xy", "choose_park"]

#: distance kept from the bed edge by a derived park spot, mm
PARK_MARGIN_MM = 5.0

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_POLY = re.compile(rb"(?m)^;\s*(bed_shape|printable_area)\s*=\s*([-+0-9.x, ]+?)\s*$")
_HEIGHT = re.compile(rb"(?m)^;\s*(?:max_print_height|printable_height)\s*=\s*(" + _NUM.encode() + rb")\s*$")
_CURA = re.compile(rb"machine_(width|depth|height|center_is_zero)\s*[=:]\s*(" + _NUM.encode() + rb"|[Tt]rue|[Ff]alse)")
_SIZE = re.compile(rb"(?m)^;\s*bed_size_([xyz])_mm\s*[:=]\s*(" + _NUM.encode() + rb")")
_KIRI = re.compile(
    rb"(?m)^;\s*Bed left:\s*(" + _NUM.encode() + rb")\s+right:\s*(" + _NUM.encode()
    + rb")\s+top:\s*(" + _NUM.encode() + rb")\s+bottom:\s*(" + _NUM.encode() + rb")"
)


@dataclass(frozen=True)
class Bed:
    """A printable bed area.

    Attributes
    ----------
    polygon : ndarray, shape (N, 2), float64
        Outline of the printable area in the file's XY frame, mm (N >= 3).
    max_z_mm : float or None
        Highest printable Z, mm, when known.
    source : str
        Where it came from (e.g. ``"bed_shape"``, ``"--bed"``), for messages.
    """

    polygon: np.ndarray
    max_z_mm: float | None
    source: str

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the outline, mm."""
        lo, hi = self.polygon.min(axis=0), self.polygon.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def describe(self) -> str:
        """Short text such as ``'5..215 x 0..220 mm (bed_shape)'``."""
        x0, y0, x1, y1 = self.bounds
        return f"X {x0:g}..{x1:g}, Y {y0:g}..{y1:g} mm ({self.source})"

    def contains(self, x: float, y: float, margin: float = 0.0) -> bool:
        """True when ``(x, y)`` lies inside the outline with at least ``margin`` mm to every edge."""
        if not (math.isfinite(x) and math.isfinite(y)):
            return False
        p = self.polygon
        q = np.roll(p, -1, axis=0)
        inside = False
        for (x0, y0), (x1, y1) in zip(p, q, strict=True):  # even-odd rule, boundary counts via the distance test
            if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
                inside = not inside
        d = _edge_distance(p, q, x, y)
        return d <= 1e-9 if not inside and margin <= 0 else inside and d >= margin - 1e-9


def _edge_distance(p: np.ndarray, q: np.ndarray, x: float, y: float) -> float:
    """Smallest distance from ``(x, y)`` to the polygon edges ``p[i] -> q[i]``, mm."""
    d = q - p
    t = np.clip(((x - p[:, 0]) * d[:, 0] + (y - p[:, 1]) * d[:, 1]) / np.maximum((d * d).sum(axis=1), 1e-18), 0, 1)
    return float(np.min(np.hypot(p[:, 0] + t * d[:, 0] - x, p[:, 1] + t * d[:, 1] - y)))


def _rect(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64)


def _checked(poly: np.ndarray, max_z: float | None, source: str) -> Bed:
    if poly.ndim != 2 or poly.shape[0] < 3 or not np.all(np.isfinite(poly)):
        raise ConfigError(f"the bed from {source} is not a polygon of at least 3 finite points; pass --bed WxH.")
    w, h = np.ptp(poly[:, 0]), np.ptp(poly[:, 1])
    if not (1.0 <= w <= 5000.0 and 1.0 <= h <= 5000.0):
        raise ConfigError(f"the bed from {source} is {w:g} x {h:g} mm, not a printer bed; pass --bed WxH.")
    if max_z is not None and not (math.isfinite(max_z) and 1.0 <= max_z <= 5000.0):
        raise ConfigError(f"the bed height from {source} is {max_z!r} mm; pass --bed WxHxZ.")
    return Bed(poly, max_z, source)


def bed_from_gcode(data: bytes) -> Bed | None:
    """The bed stated in the G-code ``data`` by its slicer, or None when it states none.

    Parameters
    ----------
    data : bytes
        ASCII G-code (a decoded ``.bgcode`` carries its metadata as comments).
    """
    hz = _HEIGHT.findall(data)
    max_z = float(hz[-1]) if hz else None
    polys = _POLY.findall(data)
    if polys:
        key, text = polys[-1]
        pts = [p.split(b"x") for p in text.replace(b" ", b"").split(b",") if p]
        try:
            poly = np.array([[float(a), float(b)] for a, b in pts], np.float64)
        except ValueError as exc:
            raise ConfigError(f"cannot read the file's {key.decode()} {text.decode()!r}; pass --bed WxH.") from exc
        return _checked(poly, max_z, key.decode())
    cura = {k.decode(): v.decode().lower() for k, v in _CURA.findall(data)}
    if "width" in cura and "depth" in cura:
        w, d = float(cura["width"]), float(cura["depth"])
        cz = float(cura["height"]) if "height" in cura else None
        x0, y0 = (-w / 2, -d / 2) if cura.get("center_is_zero") == "true" else (0.0, 0.0)
        return _checked(_rect(x0, y0, x0 + w, y0 + d), cz, "machine_width/machine_depth")
    size = {k.decode(): float(v) for k, v in _SIZE.findall(data)}
    if "x" in size and "y" in size:
        return _checked(_rect(0, 0, size["x"], size["y"]), size.get("z"), "bed_size_x_mm/bed_size_y_mm")
    kiri = _KIRI.search(data)
    if kiri:
        left, right, top, bottom = (float(v) for v in kiri.groups())
        return _checked(_rect(left, min(top, bottom), right, max(top, bottom)), None, "Kiri:Moto 'Bed'")
    return None


def parse_bed(text: str) -> Bed:
    """A ``--bed`` value: ``'220x220'``, ``'220x220x250'`` (with height), or a polygon ``'5,0;215,0;215,220;5,220'``.

    Raises
    ------
    ConfigError
        When the text is not such a value or a number is not finite.
    """
    t = text.strip().lower()
    try:
        if ";" in t:
            poly = np.array([[float(v) for v in p.split(",")] for p in t.split(";") if p.strip()], np.float64)
            if poly.ndim != 2 or poly.shape[1] != 2:
                raise ValueError(text)
            return _checked(poly, None, "--bed")
        vals = [float(v) for v in t.split("x")]
    except ValueError as exc:
        raise ConfigError(
            f"--bed {text!r}: use WxH or WxHxZ in mm (e.g. 220x220x250) or a polygon 'x,y;x,y;x,y'."
        ) from exc
    if len(vals) not in (2, 3) or not all(math.isfinite(v) and v > 0 for v in vals):
        raise ConfigError(f"--bed {text!r}: give 2 or 3 positive finite sizes in mm, e.g. 220x220 or 220x220x250.")
    return _checked(_rect(0, 0, vals[0], vals[1]), vals[2] if len(vals) == 3 else None, "--bed")


def parse_xy(text: str, option: str) -> tuple[float, float]:
    """Two finite numbers ``'X,Y'`` (mm) for ``option``, else :class:`ConfigError`."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError as exc:
        raise ConfigError(f"{option} {text!r}: give two numbers 'X,Y' in mm, e.g. 200,200.") from exc
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ConfigError(f"{option} {text!r}: the coordinates must be finite numbers in mm.")
    return x, y


def choose_park(bed: Bed, part: tuple[float, float, float, float], margin: float = PARK_MARGIN_MM) -> tuple[float, float]:
    """A park spot on ``bed``, ``margin`` mm inside its edge, as far as possible from the part.

    Candidates are the corners and edge midpoints of the bed outline pulled
    ``margin`` mm towards its centroid, kept when they lie inside the outline
    with that margin. The one farthest from the part's bounding box wins; ties
    go to the back (larger Y), then the right (larger X): out of the view of a
    camera in front of the printer.

    Parameters
    ----------
    bed : Bed
    part : (xmin, ymin, xmax, ymax)
        Bounding box of the print, mm (NaN when unknown).
    margin : float
        mm.

    Returns
    -------
    (x, y) : float, float
        mm, in the file's frame.
    """
    p = bed.polygon
    c = p.mean(axis=0)
    cands = np.concatenate([p, (p + np.roll(p, -1, axis=0)) / 2])
    vec = c - cands
    n = np.linalg.norm(vec, axis=1, keepdims=True)
    # pull each candidate inwards along both axes so a rectangle's corner ends `margin` from both edges
    cands = cands + np.sign(vec) * margin * (np.abs(vec) > 1e-9) if p.shape[0] == 4 else cands + vec / np.maximum(
        n, 1e-9) * margin * 1.5
    ok = [k for k, (x, y) in enumerate(cands) if bed.contains(float(x), float(y), margin * 0.999)]
    if not ok:
        raise ConfigError(f"the bed {bed.describe()} is too small for a park spot {margin:g} mm from its edge; "
                          "pass --park X,Y.")
    x0, y0, x1, y1 = part
    if not all(math.isfinite(v) for v in part):
        x0 = x1 = float(c[0])
        y0 = y1 = float(c[1])

    def clearance(k: int) -> tuple[float, float, float]:
        x, y = cands[k]
        dx, dy = max(x0 - x, 0.0, x - x1), max(y0 - y, 0.0, y - y1)
        return (round(math.hypot(dx, dy), 6), float(y), float(x))

    best = max(ok, key=clearance)
    return float(cands[best, 0]), float(cands[best, 1])
