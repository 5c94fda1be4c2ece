"""Failure descriptions, their resolution against a toolpath, and scenario sampling.

A :class:`Failure` is a small frozen record (type, onset layer, size, seed and
optional type parameters); :func:`resolve` turns it into concrete geometry for
one toolpath (patch centre, shift vector, object capsules, strands), drawn
deterministically from its seed. A :class:`Scenario` is a named tuple of
failures (empty = clean control).

Failure types (paper, Section 3): ``infill_defect`` (a), ``foreign_body`` (b),
``spaghetti`` (c), ``detachment`` (d), ``thin_wall`` (e), ``layer_shift`` (f);
beyond the paper, ``nothing_extruded`` (:data:`EXTRA_TYPES`): from the onset
on the nozzle prints in the air (clog, filament run-out), so the layers after
it add no material and every photo shows the last layer that was printed.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from layerwatch.errors import ConfigError
from layerwatch.gcode.toolpath import FEATURES, Toolpath
from layerwatch.geometry.topview import TopView
from layerwatch.simulate.raster import solid_area

__all__ = [
    "FAILURE_TYPES",
    "EXTRA_TYPES",
    "SIMULATED_TYPES",
    "Failure",
    "Scenario",
    "ResolvedFailure",
    "resolve",
    "thin_wall_segments",
    "selectable",
    "has_thin_walls",
    "patch_layers",
    "random_scenarios",
    "beside_point",
    "in_box",
]

FAILURE_TYPES: tuple[str, ...] = (
    "infill_defect",
    "foreign_body",
    "spaghetti",
    "detachment",
    "thin_wall",
    "layer_shift",
)
#: Failures the simulator makes beyond the paper's six (not in :func:`random_scenarios`' default mix).
EXTRA_TYPES: tuple[str, ...] = ("nothing_extruded",)
#: Every type a :class:`Failure` may have.
SIMULATED_TYPES: tuple[str, ...] = FAILURE_TYPES + EXTRA_TYPES
#: Default number of layers a patch defect stays missing: the hole deepens by one layer per
#: frame, so a sparse-infill patch (which looks like the layer below when one layer deep)
#: becomes visible as a pit.
DEFAULT_DURATION = {"infill_defect": 6, "thin_wall": 4}
_INFILL = tuple(FEATURES.index(n) for n in ("infill", "solid_infill", "top_solid_infill", "bridge"))
_WALLS = tuple(FEATURES.index(n) for n in ("perimeter", "external_perimeter"))
#: Material ids of the simulator's height field.
MAT_BED, MAT_PART, MAT_STRAND, MAT_DARK, MAT_METAL, MAT_TOOL = range(6)


@dataclass(frozen=True)
class Failure:
    """One injected failure.

    Parameters
    ----------
    type : str
        One of :data:`SIMULATED_TYPES`.
    onset : int
        First layer index (0-based) where the failure is present.
    size_mm : float
        Patch / object / strand-cloud diameter, mm; for ``layer_shift`` and
        ``detachment`` the displacement length, mm.
    seed : int
        Seed of the failure's own random choices (position, shape, direction).
    center_mm : tuple of float or None
        Where it happens on the bed, mm; None draws a point on the onset layer.
    duration : int or None
        Layers the patch stays missing (``infill_defect`` default 6,
        ``thin_wall`` default 4; the hole deepens layer by layer), or that
        ``nothing_extruded`` lasts (a clog that clears; default: to the end,
        a run-out); other types last until the end of the print.
    offset_mm : tuple of float or None
        Displacement ``(dx, dy)`` for ``layer_shift``/``detachment``; None draws
        a random direction of length ``size_mm``.
    mode : str
        ``infill_defect``: ``"missing"`` (segments removed) or ``"under"``
        (under-extruded: beads at 30 % width).
    place : str
        ``foreign_body``/``spaghetti`` without ``center_mm``: ``"on"`` draws the
        centre on the onset layer's beads, ``"beside"`` on the bed beside the
        part (:func:`beside_point`: out of the onset layer's bounding box by
        half the size plus 3 mm, on a random side).
    within_mm : tuple of float or None
        ``detachment`` only: ``(x0, y0, x1, y1)`` bed mm; only the beads whose midpoints lie in
        this box come off (one object of a multi-object plate), turning about the box's centre;
        the rest of the plate stays on the bed. None: the whole part comes off.
    """

    type: str
    onset: int
    size_mm: float = 8.0
    seed: int = 0
    center_mm: tuple[float, float] | None = None
    duration: int | None = None
    offset_mm: tuple[float, float] | None = None
    mode: str = "missing"
    place: str = "on"
    within_mm: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.type not in SIMULATED_TYPES:
            raise ConfigError(
                f"unknown failure type '{self.type}'; use one of {', '.join(SIMULATED_TYPES)}."
            )
        if self.onset < 0 or not (self.size_mm > 0 and np.isfinite(self.size_mm)):
            raise ConfigError("a failure needs onset >= 0 and a finite size_mm > 0; fix the scenario.")
        if self.mode not in ("missing", "under"):
            raise ConfigError(f"failure mode must be 'missing' or 'under', got '{self.mode}'.")
        if self.place not in ("on", "beside"):
            raise ConfigError(f"failure place must be 'on' or 'beside', got '{self.place}'.")
        if self.place == "beside" and self.type not in ("foreign_body", "spaghetti"):
            raise ConfigError(f"only foreign_body and spaghetti can be placed beside the part, not {self.type}.")
        if self.within_mm is not None and (self.type != "detachment" or not (
                self.within_mm[0] < self.within_mm[2] and self.within_mm[1] < self.within_mm[3])):
            raise ConfigError("within_mm is a detachment's (x0, y0, x1, y1) box with x0 < x1 and y0 < y1.")

    @property
    def layers(self) -> int:
        """Number of layers a patch failure lasts (``duration`` or the type's default)."""
        if self.duration is not None:
            return int(self.duration)
        return DEFAULT_DURATION.get(self.type, 1 << 30)

    def active(self, index: int) -> bool:
        """True when the failure is present in the frame taken after layer ``index``."""
        if index < self.onset:
            return False
        if self.type in ("infill_defect", "thin_wall", "nothing_extruded"):
            return index < self.onset + self.layers
        return True


@dataclass(frozen=True)
class Scenario:
    """A named set of failures for one simulated print (empty = clean control)."""

    failures: tuple[Failure, ...] = ()
    name: str = "clean"

    @property
    def label(self) -> str:
        return "+".join(f.type for f in self.failures) or "clean"


@dataclass
class ResolvedFailure:
    """A failure made concrete for one toolpath (bed mm throughout)."""

    failure: Failure
    center: np.ndarray  # (2,)
    offset: np.ndarray = field(default_factory=lambda: np.zeros(2))  # (2,)
    angle: float = 0.0  # detachment rotation, rad
    tilt: float = 0.0  # detachment tilt slope, mm/mm
    select: np.ndarray | None = None  # bool (S,) segments a patch may remove
    capsules: np.ndarray | None = None  # (N, 10) object capsules, b filled per frame
    capsule_mat: np.ndarray | None = None  # uint8 (N,)
    per_layer: int = 0  # spaghetti: strand segments added per layer

    @property
    def type(self) -> str:
        return self.failure.type


def in_box(p0: np.ndarray, p1: np.ndarray, box: tuple[float, float, float, float] | None) -> np.ndarray:
    """Beads ``p0 -> p1`` (N, 2) whose midpoints lie in ``box`` ``(x0, y0, x1, y1)`` (bed mm); all when None."""
    if box is None:
        return np.ones(len(p0), bool)
    mid = 0.5 * (p0 + p1)
    return (mid[:, 0] >= box[0]) & (mid[:, 0] <= box[2]) & (mid[:, 1] >= box[1]) & (mid[:, 1] <= box[3])


def _layer_points(tp: Toolpath, index: int, select: np.ndarray | None = None) -> np.ndarray:
    sl = tp.layer_slice(index)
    mid = 0.5 * (tp.start[sl] + tp.end[sl])
    if select is not None:
        mid = mid[select[sl]]
    return mid


def thin_wall_segments(tp: Toolpath, index: int, max_wall_mm: float = 2.2) -> np.ndarray:
    """Segments of layer ``index`` that belong to thin walls.

    A segment is in a thin wall when the layer's footprint is at most
    ``max_wall_mm`` thick around its midpoint (twice the largest inscribed
    radius within ``max_wall_mm`` of it) and that thin piece of the footprint
    is a wall: at least ``2 * max_wall_mm`` long (its bounding box). The test
    of thickness alone also takes the tips of a thick part's corners (the
    inscribed circle cannot reach into a corner: every point within 1.1 mm of
    a square corner's tip is less than 1 mm from the edge), so on a part
    without thin walls it selected a few tenths of a mm of outer perimeter at
    each corner (KISSlicer 2.0.6's cubes: 3.4 mm of beads in 95 pieces), and a
    thin-wall defect there removed about 0.1 mm^2.

    Returns
    -------
    ndarray, bool, shape (n_segments_of_layer,)
    """
    sl = tp.layer_slice(index)
    n = sl.stop - sl.start
    if n == 0:
        return np.zeros(0, bool)
    x0, y0, x1, y1 = tp.layers[index].bounds
    pad = 2.0
    tv = TopView(10.0, x1 - x0 + 2 * pad, y1 - y0 + 2 * pad, ((x0 + x1) / 2, (y0 + y1) / 2))
    fp = solid_area(tp.start[sl], tp.end[sl], tp.width[sl] / 2.0, tv).astype(np.uint8)
    dist = cv2.distanceTransform(fp, cv2.DIST_L2, 5) / tv.px_per_mm
    k = int(round(max_wall_mm * tv.px_per_mm)) | 1
    local = cv2.dilate(dist, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    thin = ((2.0 * local <= max_wall_mm) & (dist > 0)).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(thin, connectivity=8)
    long_px = 2.0 * max_wall_mm * tv.px_per_mm
    wall = np.zeros(count, bool)
    wall[1:] = np.maximum(stats[1:, cv2.CC_STAT_WIDTH], stats[1:, cv2.CC_STAT_HEIGHT]) >= long_px
    uv = np.round(tv.to_px(0.5 * (tp.start[sl] + tp.end[sl]))).astype(int)
    uv[:, 0] = uv[:, 0].clip(0, fp.shape[1] - 1)
    uv[:, 1] = uv[:, 1].clip(0, fp.shape[0] - 1)
    walls = np.isin(tp.feature[sl], _WALLS + (0,))
    return walls & wall[labels[uv[:, 1], uv[:, 0]]]


def selectable(tp: Toolpath, layer: int, kind: str) -> np.ndarray:
    """Per segment of ``layer``: which ones a patch defect of ``kind`` may remove.

    ``thin_wall``: the layer's thin walls (:func:`thin_wall_segments`), else its
    outer perimeter (a *wall gap*: the part has no thin wall there).
    ``infill_defect``: the layer's infill (sparse, solid, top, bridge); every
    bead only when the G-code marks no infill anywhere (no feature tags: Slic3r
    1.3.1). A layer that prints no infill in a file that marks it loses nothing
    (before, it lost every bead in the patch, walls included: on Cura 4.10,
    which prints sparse infill every other layer, an "infill defect" cut the
    walls on the layers between).

    Returns
    -------
    ndarray, bool, shape (n_segments_of_layer,)

    Raises
    ------
    ConfigError
        If ``kind`` is not a patch defect.
    """
    sl = tp.layer_slice(layer)
    if kind == "thin_wall":
        sel = thin_wall_segments(tp, layer)
        return sel if sel.any() else tp.feature[sl] == FEATURES.index("external_perimeter")
    if kind == "infill_defect":
        sel = np.isin(tp.feature[sl], _INFILL)
        return sel if sel.any() or _has_infill_tags(tp) else np.ones(len(sel), bool)
    raise ConfigError(f"only infill_defect and thin_wall remove segments, not {kind}.")


def has_thin_walls(tp: Toolpath, layers: range | None = None, min_segments: int = 3) -> bool:
    """Whether the part prints a thin wall (at least ``min_segments`` segments of one layer).

    Without one a ``thin_wall`` defect cuts the outer perimeter (:func:`selectable`): reports call it a
    *wall gap*. ``layers``: the layers to look at, default all (each costs a small rasterisation).
    """
    for i in layers if layers is not None else range(tp.n_layers):
        if int(thin_wall_segments(tp, i).sum()) >= min_segments:
            return True
    return False


def _selection(tp: Toolpath, f: Failure) -> np.ndarray:
    """Per-segment bool over the toolpath: :func:`selectable` on the layers of ``f``."""
    sel = np.zeros(tp.n_segments, bool)
    for i in range(f.onset, min(f.onset + f.layers, tp.n_layers)):
        sel[tp.layer_slice(i)] = selectable(tp, i, f.type)
    return sel


def _has_infill_tags(tp: Toolpath) -> bool:
    """Whether the G-code marks any infill (feature tags); without them every bead may be infill."""
    return bool(np.isin(tp.feature, _INFILL).any())


def patch_layers(rf: ResolvedFailure, tp: Toolpath) -> list[int]:
    """Layers of a resolved patch failure (``infill_defect``, ``thin_wall``) on which it removes beads.

    From the onset to the end of its duration, the layers with a selectable bead
    crossing the patch's disc (what :class:`~layerwatch.simulate.camera_sim.PrintSimulator`
    removes or under-extrudes there). A layer that prints nothing inside the patch
    is not one of them: another object's layer of a plate printed in turns
    (KISSlicer 2.0.6), or a layer without sparse infill where the slicer prints
    infill every other layer at twice the height (Cura 4.10); the photo of such a
    layer differs from the plan nowhere.

    Returns
    -------
    list of int
        Ascending layer indices (empty for other failure types).
    """
    f = rf.failure
    if f.type not in ("infill_defect", "thin_wall") or rf.select is None:
        return []
    out = []
    r2 = (f.size_mm / 2) ** 2
    for i in range(f.onset, min(f.onset + f.layers, tp.n_layers)):
        sl = tp.layer_slice(i)
        sel = rf.select[sl]
        if not sel.any():
            continue
        p0, p1 = tp.start[sl][sel], tp.end[sl][sel]
        d = p1 - p0
        t = np.clip(((rf.center - p0) * d).sum(1) / np.maximum((d * d).sum(1), 1e-12), 0.0, 1.0)
        near = p0 + t[:, None] * d - rf.center
        if ((near * near).sum(1) < r2).any():
            out.append(i)
    return out


def _strands(rng: np.random.Generator, center: np.ndarray, radius: float, n_seg: int) -> np.ndarray:
    """Smooth random-walk strands (capsules, b = NaN: draped on the surface)."""
    rows = []
    pos = center + rng.normal(0, radius / 3, 2)
    heading = rng.uniform(0, 2 * np.pi)
    turn = 0.0
    lift, phase = 1.0, 0.0
    for k in range(n_seg):
        if k % 40 == 0:  # a new strand now and then, with its own loops above the surface
            pos = center + rng.normal(0, radius / 3, 2)
            heading = rng.uniform(0, 2 * np.pi)
            lift, phase = rng.uniform(0.3, 2.5), rng.uniform(0, 2 * np.pi)
        turn = 0.8 * turn + rng.normal(0, 0.25)
        heading += turn
        if np.linalg.norm(pos - center) > radius:
            heading = np.arctan2(*(center - pos)[::-1]) + rng.normal(0, 0.5)
        step = 0.8 * np.array([np.cos(heading), np.sin(heading)])
        r = rng.uniform(0.22, 0.4)
        c = lift * abs(np.sin(0.25 * k + phase))
        rows.append([*pos, *(pos + step), r, np.nan, c, 1.6 * r, 0.1, rng.uniform(0, 6.3)])
        pos = pos + step
    return np.array(rows, dtype=np.float64).reshape(-1, 10)


def beside_point(tp: Toolpath, index: int, size_mm: float, rng: np.random.Generator) -> np.ndarray:
    """A point on the bed beside layer ``index``: out of its bounding box by ``size_mm / 2 + 3`` mm, bed mm (2,)."""
    x0, y0, x1, y1 = tp.layers[index].bounds
    gap = size_mm / 2 + 3.0
    side = int(rng.integers(4))
    t = rng.uniform(0.2, 0.8)
    if side == 0:
        return np.array([x0 - gap, y0 + t * (y1 - y0)])
    if side == 1:
        return np.array([x1 + gap, y0 + t * (y1 - y0)])
    if side == 2:
        return np.array([x0 + t * (x1 - x0), y0 - gap])
    return np.array([x0 + t * (x1 - x0), y1 + gap])


def _object(rng: np.random.Generator, center: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Capsules of a foreign object lying on the layer (b = 0: layer z added per frame)."""
    kind = rng.integers(3)
    ang = rng.uniform(0, np.pi)
    d = np.array([np.cos(ang), np.sin(ang)])
    nrm = np.array([-d[1], d[0]])
    rows, mats = [], []

    def cap(p0, p1, r, c, a, m):
        rows.append([*p0, *p1, r, 0.0, c, a, 0.0, 0.0])
        mats.append(m)

    if kind == 0:  # a dark blob (burnt plastic lump)
        for _ in range(3):
            off = rng.normal(0, size / 8, 2)
            cap(center + off - d * size / 8, center + off + d * size / 8, size / 3, 0.0, size * 0.3, MAT_DARK)
    elif kind == 1:  # a screw lying on the part
        r = max(size * 0.09, 0.6)
        a0, a1 = center - d * size / 2, center + d * size / 2
        cap(a0, a1, r, r, r, MAT_METAL)
        cap(a0 - d * r, a0 - d * r, 2.0 * r, 0.0, 2.2 * r, MAT_METAL)
    else:  # a hex key (L-shaped tool)
        r = max(size * 0.05, 0.5)
        a0, a1 = center - d * size / 2, center + d * size / 2
        cap(a0, a1, r, r, r, MAT_TOOL)
        cap(a1, a1 + nrm * size * 0.4, r, r, r, MAT_TOOL)
    return np.array(rows, np.float64), np.array(mats, np.uint8)


def resolve(f: Failure, tp: Toolpath) -> ResolvedFailure:
    """Make a failure concrete for ``tp`` (deterministic from ``f.seed``).

    Raises
    ------
    ConfigError
        If the onset layer does not exist in the toolpath.
    """
    if f.onset >= tp.n_layers:
        raise ConfigError(
            f"failure onset layer {f.onset} is beyond the print's {tp.n_layers} layers; lower it."
        )
    rng = np.random.default_rng([f.seed, SIMULATED_TYPES.index(f.type)])
    sel = _selection(tp, f) if f.type in ("infill_defect", "thin_wall") else None
    if f.center_mm is not None:
        center = np.asarray(f.center_mm, float)
    elif f.place == "beside":
        center = beside_point(tp, f.onset, f.size_mm, rng)
    else:
        pts = _layer_points(tp, f.onset, sel)
        if len(pts) == 0:
            pts = _layer_points(tp, f.onset)
        center = pts[rng.integers(len(pts))] if len(pts) else np.zeros(2)
    r = ResolvedFailure(f, center=center, select=sel)
    if f.type in ("layer_shift", "detachment"):
        if f.offset_mm is not None:
            r.offset = np.asarray(f.offset_mm, float)
        else:
            a = rng.uniform(0, 2 * np.pi)
            r.offset = f.size_mm * np.array([np.cos(a), np.sin(a)])
        if f.type == "detachment":
            b = tp.layers[f.onset].bounds if f.within_mm is None else f.within_mm
            r.center = np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])
            r.angle = np.deg2rad(rng.uniform(3.0, 8.0)) * rng.choice([-1, 1])
            r.tilt = np.tan(np.deg2rad(rng.uniform(0.5, 1.5)))
    elif f.type == "foreign_body":
        r.capsules, r.capsule_mat = _object(rng, center, f.size_mm)
    elif f.type == "spaghetti":
        r.per_layer = max(int(round(f.size_mm * 10)), 20)
        remaining = tp.n_layers - f.onset
        r.capsules = _strands(rng, center, f.size_mm / 2, r.per_layer * (remaining + 2))
        r.capsule_mat = np.full(len(r.capsules), MAT_STRAND, np.uint8)
    return r


_SIZES = {
    "infill_defect": (5.0, 12.0),
    "foreign_body": (5.0, 14.0),
    "spaghetti": (10.0, 25.0),
    "detachment": (2.0, 6.0),
    "thin_wall": (5.0, 10.0),
    "layer_shift": (1.5, 5.0),
}


def _valid_onsets(tp: Toolpath, kind: str) -> list[int]:
    first = min(2, tp.n_layers - 1)
    layers = list(range(first, tp.n_layers))
    if kind == "infill_defect":
        ok = [i for i in layers if np.isin(tp.feature[tp.layer_slice(i)], _INFILL).sum() >= 5]
        return ok or layers
    if kind == "thin_wall":
        ok = [i for i in layers if thin_wall_segments(tp, i).sum() >= 3]
        return ok or [
            i for i in layers
            if (tp.feature[tp.layer_slice(i)] == FEATURES.index("external_perimeter")).any()
        ]
    return layers


def random_scenarios(
    tp: Toolpath,
    n: int,
    seed: int = 0,
    types: tuple[str, ...] = FAILURE_TYPES,
    clean_fraction: float = 1.0 / 7.0,
    beside_fraction: float = 0.0,
) -> list[Scenario]:
    """Sample ``n`` single-failure scenarios (and clean controls) for an evaluation.

    Types cycle through ``types`` (a fraction ``clean_fraction`` of clean
    controls interleaved); onsets are drawn among layers where the type makes
    sense (infill present, thin walls present — else outer perimeters — and
    never the first two layers); sizes from a per-type range in mm. A share
    ``beside_fraction`` of the foreign bodies and spaghetti is placed on the
    bed beside the part (``place="beside"``) instead of on the onset layer.

    Returns
    -------
    list of Scenario
    """
    rng = np.random.default_rng(seed)
    onsets = {t: _valid_onsets(tp, t) for t in types}
    out: list[Scenario] = []
    kinds = list(types)
    n_clean = int(round(n * clean_fraction))
    order = ["clean"] * n_clean + [kinds[k % len(kinds)] for k in range(n - n_clean)]
    rng.shuffle(order)
    for k, kind in enumerate(order):
        if kind == "clean" or not onsets.get(kind):
            out.append(Scenario((), name=f"s{k:03d}-clean"))
            continue
        lo, hi = _SIZES[kind]
        f = Failure(
            kind,
            onset=int(rng.choice(onsets[kind])),
            size_mm=float(rng.uniform(lo, hi)),
            seed=int(rng.integers(2**31)),
            mode="under" if (kind == "infill_defect" and rng.random() < 0.3) else "missing",
            place="beside" if (kind in ("foreign_body", "spaghetti") and beside_fraction > 0
                               and rng.random() < beside_fraction) else "on",
        )
        out.append(Scenario((f,), name=f"s{k:03d}-{kind}"))
    return out


def with_onset(f: Failure, onset: int) -> Failure:
    """Copy of ``f`` starting at another layer."""
    return replace(f, onset=onset)
