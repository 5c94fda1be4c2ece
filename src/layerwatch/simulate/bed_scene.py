"""The bed when a job starts: leftover objects and the room's light since the bed photo was taken.

The empty-bed check (:mod:`layerwatch.analysis.bed_check`) compares the
camera's view at job start with the bed photo kept at calibration
(:meth:`~layerwatch.simulate.camera_sim.PrintSimulator.bed_photo`). This
module makes the photos it is evaluated on, with the simulator's own camera,
lights and sensor:

* **Leftover objects** (:class:`Leftover`, :data:`LEFTOVER_KINDS`): a part of
  the last print (a slab of filament, 0.4-8 mm high), a hex key, a screw, a
  burnt lump of plastic, a scraper blade. Each is a set of capsules of the
  simulator's height field (:mod:`layerwatch.simulate.raster`) lying on the
  bed, with the simulator's materials.
* **Light since calibration** (:class:`StartLight`): exposure, a fixed white
  balance, the spot light moved and dimmed or brightened, the ambient light;
  each start photo also has its own per-frame noise, blur and drift.

References
----------
The leftover shapes follow :func:`layerwatch.simulate.failures.resolve`'s
foreign bodies (lump, screw, hex key), lying on the bed instead of the part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from layerwatch.errors import ConfigError
from layerwatch.geometry.topview import TopView
from layerwatch.simulate import failures as fl
from layerwatch.simulate.camera_sim import PrintSimulator
from layerwatch.simulate.photo import Photographer
from layerwatch.simulate.raster import capsule_mask, stamp_capsules
from layerwatch.simulate.settings import SimSettings

__all__ = ["BED_VARIANTS", "LEFTOVER_KINDS", "Leftover", "StartLight", "leftover_capsules", "leftover_footprint",
           "random_leftover", "random_light", "start_photo"]

#: what may be left on the bed
LEFTOVER_KINDS: tuple[str, ...] = ("part", "hex_key", "screw", "lump", "scraper")

#: bed and filament colours (linear RGB) of the evaluated set-ups: the simulator's textured PEI
#: sheet with orange filament, a glass-like near-black bed, a gold PEI sheet, dark and white filament
BED_VARIANTS: dict[str, dict[str, tuple[float, float, float]]] = {
    "pei_orange": {},
    "glass_dark_filament": {"bed_rgb": (0.03, 0.033, 0.038), "filament_rgb": (0.05, 0.05, 0.055)},
    "gold_pei_white": {"bed_rgb": (0.42, 0.3, 0.12), "filament_rgb": (0.85, 0.85, 0.82)},
    "pei_dark_filament": {"filament_rgb": (0.05, 0.05, 0.055)},
}


@dataclass(frozen=True)
class Leftover:
    """One object lying on the bed.

    Parameters
    ----------
    kind : str
        One of :data:`LEFTOVER_KINDS`.
    center_mm : (float, float)
        Where it lies, bed mm.
    size_mm : float
        Its largest extent on the bed, mm (> 0).
    angle : float
        Orientation of its long axis, rad.
    height_mm : float
        Height of a leftover ``part``, mm (the other kinds have their own).
    """

    kind: str
    center_mm: tuple[float, float]
    size_mm: float
    angle: float = 0.0
    height_mm: float = 2.0

    def __post_init__(self) -> None:
        if self.kind not in LEFTOVER_KINDS:
            raise ConfigError(f"unknown leftover kind {self.kind!r}; use one of {', '.join(LEFTOVER_KINDS)}.")
        if not (np.isfinite(self.size_mm) and self.size_mm > 0 and np.isfinite(self.height_mm) and self.height_mm > 0):
            raise ConfigError("a leftover needs a finite size_mm > 0 and height_mm > 0.")


def _slab(rows: list, mats: list, a0: np.ndarray, d: np.ndarray, n: np.ndarray, length: float, width: float,
          height: float, mat: int) -> None:
    """Parallel capsules filling a ``length`` x ``width`` x ``height`` box from ``a0`` along ``d``."""
    k = max(int(np.ceil(width / 0.45)), 1)
    r = 0.5 * width / k + 0.1
    top = max(height - 0.15, 0.05)
    for j in range(k):
        off = n * ((j + 0.5) * width / k - width / 2)
        p0, p1 = a0 + off + d * r, a0 + off + d * (length - r)
        rows.append([*p0, *p1, r, 0.0, top - min(0.15, top / 2), min(0.15, top / 2), 0.0, 0.0])
        mats.append(mat)


def leftover_capsules(obj: Leftover) -> tuple[np.ndarray, np.ndarray]:
    """Capsule rows (:func:`~layerwatch.simulate.raster.stamp_capsules`, base 0: on the bed) and materials.

    Returns
    -------
    rows : ndarray, float64, shape (N, 10)
    mats : ndarray, uint8, shape (N,)
    """
    c = np.asarray(obj.center_mm, float)
    d = np.array([np.cos(obj.angle), np.sin(obj.angle)])
    n = np.array([-d[1], d[0]])
    s = float(obj.size_mm)
    rows: list = []
    mats: list = []

    def cap(p0, p1, r, height, mat):
        rows.append([*p0, *p1, r, 0.0, height / 2, height / 2, 0.0, 0.0])
        mats.append(mat)

    if obj.kind == "part":  # a piece of the last print: a slab of filament
        _slab(rows, mats, c - d * s / 2, d, n, s, 0.55 * s, obj.height_mm, fl.MAT_PART)
    elif obj.kind == "hex_key":  # L-shaped tool, 1-2.5 mm thick
        r = float(np.clip(s * 0.05, 0.5, 1.25))
        a0, a1 = c - d * s / 2, c + d * s / 2
        cap(a0, a1, r, 2 * r, fl.MAT_TOOL)
        cap(a1, a1 + n * s * 0.35, r, 2 * r, fl.MAT_TOOL)
    elif obj.kind == "screw":  # shank and head
        r = max(s * 0.09, 0.8)
        a0, a1 = c - d * s / 2, c + d * s / 2
        cap(a0, a1, r, 2 * r, fl.MAT_METAL)
        cap(a0 - d * r, a0 - d * r, 2.0 * r, 2.2 * r, fl.MAT_METAL)
    elif obj.kind == "lump":  # burnt plastic purged at the last start
        for k in range(3):
            off = (k - 1) * d * s / 4
            cap(c + off - d * s / 8, c + off + d * s / 8, s / 3.2, s * 0.25, fl.MAT_DARK)
    else:  # scraper: a thin metal blade and a dark handle
        _slab(rows, mats, c - d * s / 2, d, n, 0.45 * s, 0.5 * s, 0.6, fl.MAT_METAL)
        _slab(rows, mats, c - d * s * 0.05, d, n, 0.55 * s, 0.22 * s, 0.22 * s, fl.MAT_DARK)
    return np.array(rows, np.float64).reshape(-1, 10), np.array(mats, np.uint8)


def leftover_footprint(objs: tuple[Leftover, ...] | list[Leftover], topview: TopView) -> np.ndarray:
    """Where the objects touch the bed, top-view bool mask (``topview.shape``)."""
    out = np.zeros(topview.shape, bool)
    for obj in objs:
        rows, _ = leftover_capsules(obj)
        out |= capsule_mask(rows[:, 0:2], rows[:, 2:4], rows[:, 4], topview)
    return out


@dataclass(frozen=True)
class StartLight:
    """How the light at job start differs from the bed photo's.

    Attributes
    ----------
    exposure : float
        Exposure factor (auto-exposure, another time of day).
    white_balance : (float, float, float)
        Fixed per-channel gain, BGR (auto white balance, another lamp).
    light_shift_mm : (float, float, float)
        Where the spot light moved, camera frame (right, along the view, up), mm.
    intensity : float
        Spot light factor.
    ambient : float
        Ambient light factor.
    """

    exposure: float = 1.0
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    light_shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    intensity: float = 1.0
    ambient: float = 1.0

    def settings(self, base: SimSettings) -> SimSettings:
        """``base`` with this light."""
        off = tuple(float(a + b) for a, b in zip(base.light_offset_mm, self.light_shift_mm, strict=True))
        return base.model_copy(update={
            "exposure": base.exposure * self.exposure,
            "white_balance": tuple(float(a * b) for a, b in zip(base.white_balance, self.white_balance, strict=True)),
            "light_offset_mm": off,
            "light_intensity": base.light_intensity * self.intensity,
            "ambient": base.ambient * self.ambient,
        })


def random_light(rng: np.random.Generator, strength: float = 1.0) -> StartLight:
    """A plausible change of light since the bed photo: exposure 0.7-1.4 x, white balance +-10 %,
    the spot light moved by ~30 mm and 0.8-1.2 x as bright, ambient 0.7-1.3 x (``strength`` scales the changes)."""
    e = float(np.exp(rng.uniform(np.log(0.7), np.log(1.4)) * strength))
    wb = tuple(float(1 + strength * v) for v in rng.uniform(-0.1, 0.1, 3))
    shift = tuple(float(v) for v in rng.normal(0, 30.0 * strength, 3))
    return StartLight(e, wb, shift, float(1 + strength * rng.uniform(-0.2, 0.2)),  # type: ignore[arg-type]
                      float(1 + strength * rng.uniform(-0.3, 0.3)))


def random_leftover(topview: TopView, rng: np.random.Generator, size_mm: tuple[float, float] = (10.0, 40.0),
                    kinds: tuple[str, ...] = LEFTOVER_KINDS, avoid_mm: np.ndarray | None = None) -> Leftover:
    """An object of a random kind and size lying inside the observed square (its extent inside, off the markers).

    Parameters
    ----------
    topview : TopView
        The observed square.
    size_mm : (float, float)
        Range of the object's size, mm.
    avoid_mm : ndarray, shape (K, 2), optional
        Points (the bed markers) the object keeps 8 mm plus its half size away from.
    """
    kind = str(kinds[int(rng.integers(len(kinds)))])
    s = float(rng.uniform(*size_mm))
    corners = topview.corners_mm
    (x0, y0), (x1, y1) = corners.min(0), corners.max(0)
    pad = s / 2 + 3.0
    for _ in range(100):
        c = np.array([rng.uniform(x0 + pad, x1 - pad), rng.uniform(y0 + pad, y1 - pad)])
        if avoid_mm is None or np.min(np.linalg.norm(np.asarray(avoid_mm) - c, axis=1)) > 8.0 + s / 2:
            break
    return Leftover(kind, (float(c[0]), float(c[1])), s, float(rng.uniform(0, np.pi)), float(rng.uniform(0.4, 8.0)))


def start_photo(sim: PrintSimulator, leftovers: tuple[Leftover, ...] | list[Leftover] = (),
                light: StartLight | None = None, index: int = 0) -> np.ndarray:
    """The camera's view of the bed when a job starts, before anything is printed.

    Parameters
    ----------
    sim : PrintSimulator
        The printer, camera and bed (its seed is the bed's texture, as in :meth:`PrintSimulator.bed_photo`).
    leftovers : sequence of Leftover
        Objects on the bed.
    light : StartLight, optional
        The light at job start (default: the simulator's).
    index : int
        Frame number of the start photo (its own noise, blur and light jitter).

    Returns
    -------
    ndarray, uint8, shape (h, w, 3)
        BGR photo.
    """
    st = (light or StartLight()).settings(sim.settings)
    cam = Photographer(sim.camera, sim.topview, sim.grid, st, sim.seed)
    h = np.zeros(sim.grid.shape, np.float32)
    mat = np.zeros(sim.grid.shape, np.uint8)
    for obj in leftovers:
        rows, mats = leftover_capsules(obj)
        stamp_capsules(h, mat, h.copy(), rows, mats, *sim.gp)
    photo, _ = cam.shoot(h, mat, sim.tp.n_layers + 2000 + int(index), 0.2)
    return photo
