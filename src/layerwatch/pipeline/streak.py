"""Layers in a row on which a rule alarmed in the same place.

A real failure stays where it is; noise lands at random places. Rules 4, 4b
and the per-kind thresholds of :class:`~layerwatch.pipeline.policy.PausePolicy`
count alarmed layers in a row only while each layer's regions overlap those
of the previous alarmed layer: :class:`PlaceStreak` is that count. Places are
the regions' bounding boxes in bed coordinates, mm.
"""

from __future__ import annotations

from collections.abc import Sequence

from layerwatch.analysis.result import Region

__all__ = ["PlaceStreak", "boxes_overlap"]


def boxes_overlap(a: Sequence[float], b: Sequence[float]) -> bool:
    """Whether two bounding boxes ``(x0, y0, x1, y1)`` (mm) overlap; touching counts."""
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


def any_overlap(regions: Sequence[Region], others: Sequence[Region]) -> bool:
    """Whether any region of ``regions`` overlaps any of ``others`` (bounding boxes)."""
    return any(boxes_overlap(tuple(r.bbox_mm), tuple(p.bbox_mm)) for r in regions for p in others)


class PlaceStreak:
    """Alarmed layers in a row whose regions overlap those of the previous alarmed layer.

    A layer without regions, or after a layer without regions, continues the
    streak (a% without regions is trusted); a layer whose regions lie
    elsewhere starts a new streak of 1; a layer without alarm ends it.

    Attributes
    ----------
    count : int
        Alarmed layers in a row, 0 after a layer without alarm or :meth:`reset`.
    regions : list of Region
        The regions of the last alarmed layer ([] after a layer without alarm).
    """

    def __init__(self) -> None:
        self.count = 0
        self.regions: list[Region] = []

    def reset(self) -> None:
        """Start afresh (operator resumed, an object cancelled, a quiet gap)."""
        self.count, self.regions = 0, []

    def step(self, alarm: bool, regions: Sequence[Region] = ()) -> int:
        """Count one layer; returns the streak after it.

        Parameters
        ----------
        alarm : bool
            The rule alarmed on this layer.
        regions : sequence of Region
            The regions behind the alarm.
        """
        if not alarm:
            self.reset()
            return 0
        same = not regions or not self.regions or any_overlap(regions, self.regions)
        self.count = self.count + 1 if (same and self.count) else 1
        self.regions = list(regions)
        return self.count
