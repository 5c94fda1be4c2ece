"""Printable bed-marker sheets for ``layerwatch calibrate --markers``.

A :class:`MarkerLayout` fixes four markers in *bed* millimetres (the
G-code's frame, +Y towards the back of the printer). By default they sit at
the corners of the observed square of the top view (90 x 90 mm, centred on
the bed), exactly where :func:`~layerwatch.geometry.pose.marker_layout`
looks for them when ``[markers] positions_mm`` is not set; the layout also
writes that TOML section so the pose never depends on a default.

Marks as :mod:`~layerwatch.geometry.markers` detects them:

* ``"dots"``: a white disc of ``size_mm`` (default ``MarkerSettings.diameter_mm``,
  6 mm) on a black square of ``DOT_PATCH`` x the diameter. The detector
  looks for white discs on a *darker* surround (white top-hat, background
  taken from the ring around the disc), so the black square is what makes a
  dot on white paper detectable, and the disc's printed size must be exact
  (:func:`~layerwatch.geometry.pose.locate_bed` refuses a dot whose imaged
  area is off by 2x).
* ``"aruco"``: tag id ``i`` (``DICT_4X4_50`` by default) of side ``size_mm``
  centred on ``positions_mm[i]``, drawn as vector cells, with the paper as
  its white quiet zone.

Pages are drawn with matplotlib in page millimetres (origin bottom-left,
+y up = bed +Y), at 1:1: PDF and SVG keep millimetres; PNG is rasterised
at ``dpi``. Each mark carries its bed coordinates; every page has a
100 mm scale bar to check that the printer did not scale the page.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from layerwatch.errors import ConfigError
from layerwatch.geometry.markers import _aruco_dictionary
from layerwatch.geometry.settings import MarkerSettings, TopViewSettings

__all__ = ["MarkerLayout", "SheetPage", "plan_layout", "plan_pages", "parse_pair", "write_sheet",
           "PAPERS", "DOT_PATCH"]

PAPERS = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}
DOT_PATCH = 4.0  # side of the black square around a dot, in dot diameters
BED_RANGE_MM = (50.0, 2000.0)
DOT_RANGE_MM = (2.0, 30.0)
TAG_RANGE_MM = (10.0, 100.0)
MARGIN_MM = 12.0  # paper border left blank (printers cannot print to the edge)
LABEL_MM = 9.0  # room for a mark's coordinate label
HEADER_MM = 26.0  # title and orientation lines at the top of a page
FOOTER_MM = 30.0  # scale bar and its note at the bottom of a page
SCALE_BAR_MM = 100.0


def parse_pair(text: str, option: str, sep: str = ",") -> tuple[float, float]:
    """Two finite numbers from ``"A<sep>B"`` (``"220x220"``, ``"110,110"``); ConfigError naming ``option``."""
    parts = str(text).lower().replace(" ", "").split(sep)
    try:
        a, b = (float(p) for p in parts)
    except ValueError:
        raise ConfigError(f"{option} {text!r} is not two numbers A{sep}B; write e.g. "
                          f"{'220x220' if sep == 'x' else '110,110'}.") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise ConfigError(f"{option} {text!r} must be finite numbers.")
    return a, b


@dataclass(frozen=True)
class MarkerLayout:
    """Four markers on the bed and what to print.

    Attributes
    ----------
    kind : {"dots", "aruco"}
    positions_mm : ndarray, shape (4, 2)
        Marker centres in bed mm, ordered front-left, front-right, back-right,
        back-left (:attr:`TopView.corners_mm` order; ArUco id ``i`` at row ``i``).
    size_mm : float
        Dot diameter or tag side, mm.
    center_mm, side_mm :
        Centre and side of the square the markers span (= the observed square
        of the top view written by :meth:`config_toml`), mm.
    bed_min_mm, bed_size_mm :
        Bed rectangle: front-left corner in G-code coordinates and ``(width, depth)``, mm.
    dictionary : str
        ArUco dictionary name (``kind == "aruco"``).
    """

    kind: str
    positions_mm: np.ndarray
    size_mm: float
    center_mm: tuple[float, float]
    side_mm: float
    bed_min_mm: tuple[float, float]
    bed_size_mm: tuple[float, float]
    dictionary: str = "DICT_4X4_50"

    @property
    def half_extent_mm(self) -> float:
        """Half the side of the printed area of one mark (dark square, or tag plus quiet zone), mm."""
        return self.size_mm * (DOT_PATCH / 2 if self.kind == "dots" else 0.75)

    def config_toml(self) -> str:
        """``[topview]`` and ``[markers]`` sections of a job config for this layout."""
        pos = ", ".join(f"[{_num(x)}, {_num(y)}]" for x, y in self.positions_mm)
        lines = ["[topview]", f"center_mm = [{_num(self.center_mm[0])}, {_num(self.center_mm[1])}]",
                 f"width_mm = {_num(self.side_mm)}", f"height_mm = {_num(self.side_mm)}", "",
                 "[markers]", f'kind = "{self.kind}"', f"positions_mm = [{pos}]"]
        if self.kind == "dots":
            lines.append(f"diameter_mm = {_num(self.size_mm)}")
        else:
            lines.append(f'aruco_dictionary = "{self.dictionary}"')
        return "\n".join(lines) + "\n"

    def label(self, i: int) -> str:
        """Text printed beside mark ``i``: its index and bed coordinates."""
        x, y = self.positions_mm[i]
        name = f"id {i}" if self.kind == "aruco" else f"mark {i}"
        return f"{name}: X{_num(x)} Y{_num(y)}"


def _num(v: float) -> str:
    return f"{float(v):.2f}".rstrip("0").rstrip(".")


def _check_range(value: float, lo: float, hi: float, what: str, fix: str) -> None:
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ConfigError(f"{what} {value:g} mm is outside {lo:g}..{hi:g} mm; {fix}.")


def plan_layout(bed_size_mm: tuple[float, float], *, kind: str = "dots", side_mm: float | None = None,
                center_mm: tuple[float, float] | None = None, bed_min_mm: tuple[float, float] = (0.0, 0.0),
                size_mm: float | None = None, dictionary: str = "DICT_4X4_50") -> MarkerLayout:
    """Place four markers at the corners of a square on the bed, checking that every mark fits on it.

    Parameters
    ----------
    bed_size_mm : (float, float)
        Bed width (X) and depth (Y), mm, each in ``BED_RANGE_MM``.
    kind : {"dots", "aruco"}
    side_mm : float or None
        Side of the marker square, mm (default: the top view's 90 mm, less on
        a bed too small for it).
    center_mm : (float, float) or None
        Its centre in bed mm (default: the bed's centre).
    bed_min_mm : (float, float)
        G-code coordinates of the bed's front-left corner (``(0, 0)`` on most
        printers; ``(-W/2, -D/2)`` when the origin is the bed centre).
    size_mm : float or None
        Dot diameter (default ``MarkerSettings.diameter_mm``) or tag side (default 25 mm).

    Raises
    ------
    ConfigError
        A value is not finite or out of range, or a mark would not lie on the bed.
    """
    if kind not in ("dots", "aruco"):
        raise ConfigError(f"--kind {kind!r} is unknown; use dots or aruco.")
    w, d = (float(v) for v in bed_size_mm)
    for v, axis in ((w, "width"), (d, "depth")):
        _check_range(v, *BED_RANGE_MM, f"bed {axis}", "give the bed as WIDTHxDEPTH in mm, e.g. --bed 220x220")
    x0, y0 = (float(v) for v in bed_min_mm)
    _check_range(abs(x0), 0.0, 10_000.0, "bed origin X", "give --origin X,Y of the bed's front-left corner")
    _check_range(abs(y0), 0.0, 10_000.0, "bed origin Y", "give --origin X,Y of the bed's front-left corner")
    dots = kind == "dots"
    if not dots:
        _aruco_dictionary(dictionary)  # an unknown name fails here, before anything is written
    size = float(size_mm if size_mm is not None else (MarkerSettings().diameter_mm if dots else 25.0))
    _check_range(size, *(DOT_RANGE_MM if dots else TAG_RANGE_MM), "--size", "choose a printable mark size")
    half = size * (DOT_PATCH / 2 if dots else 0.75)
    # default: the top view's observed square, shrunk on a small bed to leave 5 mm around the marks
    side = float(side_mm if side_mm is not None else min(TopViewSettings().width_mm, min(w, d) - 2 * half - 10))
    cx, cy = (float(v) for v in (center_mm if center_mm is not None else (x0 + w / 2, y0 + d / 2)))
    if not (math.isfinite(side) and math.isfinite(cx) and math.isfinite(cy)):
        raise ConfigError("--side and --center must be finite numbers.")
    if not side >= 2 * half + 5:
        raise ConfigError(f"--side {side:g} mm is too small for marks of {size:g} mm (they would overlap); "
                          f"use at least {2 * half + 5:g} mm.")
    pos = np.array([[cx - side / 2, cy - side / 2], [cx + side / 2, cy - side / 2],
                    [cx + side / 2, cy + side / 2], [cx - side / 2, cy + side / 2]])
    lo, hi = pos.min(0) - half, pos.max(0) + half
    if lo[0] < x0 or lo[1] < y0 or hi[0] > x0 + w or hi[1] > y0 + d:
        raise ConfigError(f"the marks ({_num(lo[0])}..{_num(hi[0])} x {_num(lo[1])}..{_num(hi[1])} mm) do not fit "
                          f"the bed {_num(x0)}..{_num(x0 + w)} x {_num(y0)}..{_num(y0 + d)} mm; "
                          "use a smaller --side or move --center.")
    return MarkerLayout(kind, pos, size, (cx, cy), side, (x0, y0), (w, d), dictionary)


@dataclass(frozen=True)
class SheetPage:
    """One printed page: its size and where bed points land on it.

    ``page_xy = bed_xy + offset_mm`` (page mm, origin bottom-left, +y up);
    ``marks`` are the indices of the layout's markers drawn on this page.
    """

    size_mm: tuple[float, float]
    offset_mm: tuple[float, float]
    marks: tuple[int, ...]

    def page_from_bed(self, xy_mm: np.ndarray) -> np.ndarray:
        """Bed mm (..., 2) -> page mm (..., 2)."""
        return np.asarray(xy_mm, float) + np.asarray(self.offset_mm, float)

    def pixels(self, xy_mm: np.ndarray, dpi: float) -> np.ndarray:
        """Bed mm (..., 2) -> ``(u, v)`` px of this page rendered at ``dpi`` (OpenCV pixel centres)."""
        p = self.page_from_bed(xy_mm)
        s = dpi / 25.4
        return np.stack([p[..., 0] * s - 0.5, (self.size_mm[1] - p[..., 1]) * s - 0.5], axis=-1)


def plan_pages(layout: MarkerLayout, paper: str = "a4", tiles: bool = False) -> list[SheetPage]:
    """The pages of a sheet: one page with all four marks, or (``tiles``) one page per mark.

    Raises
    ------
    ConfigError
        Unknown paper, or the marks do not fit one page (use ``tiles``).
    """
    if paper not in PAPERS:
        raise ConfigError(f"--paper {paper!r} is unknown; use {' or '.join(PAPERS)}.")
    pw, ph = PAPERS[paper]
    free_h = ph - 2 * MARGIN_MM - HEADER_MM - FOOTER_MM
    if tiles:
        return [SheetPage((pw, ph), (pw / 2 - x, MARGIN_MM + FOOTER_MM + free_h / 2 - y), (i,))
                for i, (x, y) in enumerate(layout.positions_mm)]
    h = layout.half_extent_mm
    need_w = layout.side_mm + 2 * h
    need_h = layout.side_mm + 2 * h + 2 * LABEL_MM
    if need_w > pw - 2 * MARGIN_MM or need_h > free_h:
        raise ConfigError(f"the marks span {_num(need_w)} x {_num(need_h)} mm, more than one {paper} page holds; "
                          "add --tiles (one page per mark) or use a smaller --side.")
    cx, cy = layout.center_mm
    return [SheetPage((pw, ph), (pw / 2 - cx, MARGIN_MM + FOOTER_MM + free_h / 2 - cy), (0, 1, 2, 3))]


def _draw_dot(ax, xy, d) -> None:
    s = DOT_PATCH * d
    ax.add_patch(Rectangle((xy[0] - s / 2, xy[1] - s / 2), s, s, facecolor="black", edgecolor="none"))
    ax.add_patch(Circle(xy, d / 2, facecolor="white", edgecolor="none"))


def _draw_tag(ax, xy, side, tag_id, dictionary) -> None:
    """ArUco tag ``tag_id`` as vector cells (black where the marker image is 0)."""
    d = _aruco_dictionary(dictionary)
    cells = d.markerSize + 2
    bits = cv2.aruco.generateImageMarker(d, tag_id, cells, borderBits=1)
    c = side / cells
    x0, y1 = xy[0] - side / 2, xy[1] + side / 2
    for r, col in zip(*np.nonzero(bits < 128), strict=True):
        ax.add_patch(Rectangle((x0 + col * c, y1 - (r + 1) * c), c, c, facecolor="black", edgecolor="none",
                               antialiased=False))


def _draw_scale_bar(ax, page: SheetPage) -> None:
    x0 = (page.size_mm[0] - SCALE_BAR_MM) / 2
    y0 = MARGIN_MM + 14.0
    ax.add_patch(Rectangle((x0, y0), SCALE_BAR_MM, 2.0, facecolor="black", edgecolor="none"))
    for k in range(0, int(SCALE_BAR_MM) + 1, 10):
        tick = 4.0 if k % 50 == 0 else 2.5
        ax.add_patch(Rectangle((x0 + k - 0.15, y0 - tick), 0.3, tick, facecolor="black", edgecolor="none"))
    ax.text(x0 + SCALE_BAR_MM / 2, y0 + 3.5, f"{SCALE_BAR_MM:g} mm", ha="center", va="bottom", fontsize=9)
    ax.text(page.size_mm[0] / 2, MARGIN_MM, "Measure this bar: it must be exactly 100 mm. If not, print again at "
            "100 % / \"actual size\" (no \"fit to page\").", ha="center", va="bottom", fontsize=7.5)


def _draw_text(ax, layout: MarkerLayout, page: SheetPage, n_pages: int) -> None:
    pw, ph = page.size_mm
    w, d = layout.bed_size_mm
    what = (f"4 white dots {_num(layout.size_mm)} mm" if layout.kind == "dots"
            else f"ArUco {layout.dictionary} {_num(layout.size_mm)} mm")
    title = f"layerwatch bed markers · bed {_num(w)} x {_num(d)} mm · {what} · 1:1"
    if n_pages > 1:
        title += f" · page {page.marks[0] + 1} of {n_pages}"
    ax.text(pw / 2, ph - MARGIN_MM, title, ha="center", va="top", fontsize=10, weight="bold")
    ax.text(pw / 2, ph - MARGIN_MM - 7, "BACK of the bed (+Y) ↑ — this edge away from you", ha="center",
            va="top", fontsize=8)
    i = page.marks[0]
    x, y = layout.positions_mm[i]
    ax.text(pw / 2, ph - MARGIN_MM - 13, f"Place: move the nozzle to X{_num(x)} Y{_num(y)} and slide the sheet until "
            f"it is over the centre of {'id' if layout.kind == 'aruco' else 'mark'} {i}; tape flat.",
            ha="center", va="top", fontsize=7.5)


def draw_page(layout: MarkerLayout, page: SheetPage, n_pages: int = 1):
    """A matplotlib ``Figure`` of one page at 1:1 (figure inches = page mm / 25.4)."""
    pw, ph = page.size_mm
    fig = Figure(figsize=(pw / 25.4, ph / 25.4))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0, pw)
    ax.set_ylim(0, ph)
    ax.set_aspect("auto")
    ax.axis("off")
    h = layout.half_extent_mm
    for i in page.marks:
        xy = page.page_from_bed(layout.positions_mm[i])
        if layout.kind == "dots":
            _draw_dot(ax, xy, layout.size_mm)
        else:
            _draw_tag(ax, xy, layout.size_mm, i, layout.dictionary)
        front = layout.positions_mm[i][1] < layout.center_mm[1] or len(page.marks) == 1
        ty = xy[1] - h - 2.0 if front else xy[1] + h + 2.0
        ax.text(xy[0], ty, layout.label(i), ha="center", va="top" if front else "bottom", fontsize=8)
    _draw_text(ax, layout, page, n_pages)
    _draw_scale_bar(ax, page)
    return fig


def write_sheet(layout: MarkerLayout, path: str | Path, *, paper: str = "a4", tiles: bool = False,
                dpi: float = 300.0) -> list[tuple[Path, SheetPage]]:
    """Write the sheet as PDF (all pages in one file), SVG or PNG (one file per page: ``NAME-1.svg`` ...).

    Parameters
    ----------
    path : str or Path
        Output file; its suffix picks the format.
    dpi : float
        PNG resolution, dots per inch (``dpi / 25.4`` px per mm), 72..1200.

    Returns
    -------
    list of (Path, SheetPage)
        Each written file with the page it holds (the PDF's entries share the path).

    Raises
    ------
    ConfigError
        Unknown suffix, dpi out of range, or the folder is not writable.
    """
    out = Path(path)
    fmt = out.suffix.lower().lstrip(".")
    if fmt not in ("pdf", "svg", "png"):
        raise ConfigError(f"-o {out}: unknown format {out.suffix or '(no suffix)'!r}; name the file .pdf, .svg or .png.")
    if not (math.isfinite(dpi) and 72 <= dpi <= 1200):
        raise ConfigError(f"--dpi {dpi:g} is outside 72..1200; 300 suits most printers.")
    pages = plan_pages(layout, paper, tiles)
    if not out.parent.is_dir():
        raise ConfigError(f"-o {out}: the folder {out.parent} does not exist; create it first.")
    written: list[tuple[Path, SheetPage]] = []
    try:
        if fmt == "pdf":
            with PdfPages(out) as pdf:
                for page in pages:
                    pdf.savefig(draw_page(layout, page, len(pages)))
                    written.append((out, page))
            return written
        for k, page in enumerate(pages, start=1):
            target = out if len(pages) == 1 else out.with_name(f"{out.stem}-{k}{out.suffix}")
            draw_page(layout, page, len(pages)).savefig(target, format=fmt, dpi=dpi)
            written.append((target, page))
    except OSError as exc:
        raise ConfigError(f"cannot write {out}: {exc.strerror or exc}; choose another -o.") from None
    return written
