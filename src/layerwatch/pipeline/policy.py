"""When a stream of :class:`LayerResult` should pause the print: the one pause policy.

The monitor, ``analyze``, the demo and the evaluation's false-alarm count all
feed :class:`PausePolicy`; :class:`Decision` is the one type of its answer.

Rules (all thresholds in :class:`PolicySettings`):

1. ``a%`` of the anomaly not acknowledged above ``pause_ratio`` (and at least
   ``min_area_mm2`` of it) for ``consecutive_layers`` analysed layers
   in a row, with a failing region in the same place on consecutive layers
   (noise spikes land at random places) -> ``settings.action``; a single layer above it -> ``notify``
   (when ``notify_single_layer``).
2. A failing region that overlaps one of the previous analysed layer and has
   grown by ``growth_ratio`` (and is at least ``growth_min_area_mm2``) ->
   ``settings.action``.
3. One strong event: anomalous area outside the footprint above
   ``strong_outside_area_mm2`` -> ``settings.strong_action``.
4. The scene channel's change beside the print (``outside_anomalous_mm2``,
   ``outside_regions``; off when ``outside_pause_mm2`` is 0): at least
   ``outside_pause_mm2`` not acknowledged on ``consecutive_layers`` analysed
   layers in a row, in overlapping places -> ``settings.action``; one such
   layer -> ``notify``.

5. A failed check (:attr:`LayerResult.failed_check`: the bed is not empty at
   job start, the first layer failed, nothing extruded on two layers in a
   row; :mod:`layerwatch.pipeline.checks`) -> ``settings.action`` at once:
   each check already asks for its own evidence, and what it found is in
   ``check_regions`` with its kind.

Errors (camera, warp, printer) never pause: they give ``notify``. After a
pause the policy stays quiet until :meth:`PausePolicy.acknowledge` (the
operator resumed); the regions seen at that moment are then ignored unless
they grow beyond ``growth_ratio`` times their acknowledged area.

References
----------
Petsiuk & Pearce (2022), eq. (5) for ``a%``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Literal

from pydantic import Field

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.settings_base import Section

__all__ = ["Decision", "NotifySettings", "PausePolicy", "PolicySettings", "first_stop"]

Action = Literal["none", "notify", "pause", "cancel"]


class PolicySettings(Section):
    """When the stream of layer results pauses the print (config section ``[policy]``).

    The built-in values below are the paper-era defaults; the product runs the
    evaluation's recommended values over them (``pause_ratio = 0.025``,
    :data:`layerwatch.pipeline.config.RECOMMENDED`, shown with their source by
    ``layerwatch config show``). :meth:`PausePolicy.update` applies them as
    follows (errors and skipped layers never pause; the first
    ``skip_first_layers`` layers are never judged):

    * **ratio rule**: a layer *alarms* when the anomalous area the operator has
      not acknowledged is above ``pause_ratio`` of the printed area (eq. 5)
      *and* at least ``min_area_mm2``; ``consecutive_layers`` alarms in a row
      whose failing regions overlap those of the previous layer -> ``action``;
      a single alarm -> ``"notify"`` when ``notify_single_layer``;
    * **growth rule**: a region of at least ``growth_min_area_mm2`` that
      overlaps one of the previous layer and is ``growth_ratio`` times its area
      (or outgrew its acknowledged area that much) -> ``action``;
    * **strong event**: more than ``strong_outside_area_mm2`` of anomalous area
      outside the footprint -> ``strong_action`` (0 disables it);
    * **outside rule** (the scene channel, :mod:`layerwatch.pipeline.scene`):
      at least ``outside_pause_mm2`` of change beside the print that the
      operator has not acknowledged, on ``consecutive_layers`` layers in a
      row with overlapping outside regions -> ``action``; a single such layer
      -> ``"notify"`` (when ``notify_single_layer``). 0 disables it (the
      paper's settings); the recommended 12 mm^2 is three 2 x 2 mm blocks
      and above every clean layer of the evaluation (``docs/architecture.md``).

    ``wait_for_verdict`` is read by the monitor: hold the printer until the
    layer is judged.

    Attributes
    ----------
    pause_ratio : float
        a% limit as a fraction in [0, 1] (default 0.10; recommended 0.025).
    min_area_mm2 : float
        Fresh anomalous area the ratio rule also needs, mm^2 (a small footprint
        crosses any ratio with two or three 1.44 mm^2 blocks).
    consecutive_layers : int
        Alarmed layers in a row before ``action``.
    strong_outside_area_mm2 : float
        Anomalous area outside the footprint for the strong event, mm^2.
    growth_ratio : float
        Area factor of the growth rule (also how much acknowledged anomaly must grow).
    growth_min_area_mm2 : float
        Smallest region the growth rule looks at, mm^2.
    action, strong_action : {"notify", "pause", "cancel"}
    skip_first_layers : int
    outside_pause_mm2 : float
        Change beside the print for the outside rule, mm^2 (0 = off).
    notify_single_layer : bool
    wait_for_verdict : bool
    """

    pause_ratio: float = Field(0.10, ge=0, le=1)
    min_area_mm2: float = Field(5.0, ge=0)
    consecutive_layers: int = Field(2, ge=1)
    strong_outside_area_mm2: float = Field(150.0, ge=0)
    growth_ratio: float = Field(1.5, ge=1)
    action: Literal["notify", "pause", "cancel"] = "pause"
    wait_for_verdict: bool = False
    skip_first_layers: int = Field(1, ge=0)
    growth_min_area_mm2: float = Field(25.0, ge=0)
    strong_action: Literal["notify", "pause", "cancel"] = "pause"
    notify_single_layer: bool = True
    outside_pause_mm2: float = Field(0.0, ge=0)


class NotifySettings(Section):
    """Where the policy's alerts go (config section ``[notify]``): Apprise URLs and/or a JSON webhook, rate-limited.

    It sits beside :class:`PolicySettings` because it completes the policy's
    ``"notify"`` action; the monitor's :mod:`~layerwatch.monitor.notify` sends.

    Attributes
    ----------
    apprise_urls : list of str
    webhook_url : str or None
    min_interval_s : float
        Smallest interval between two non-critical alerts, s.
    """

    apprise_urls: list[str] = Field(default_factory=list)
    webhook_url: str | None = None
    min_interval_s: float = Field(60.0, ge=0)


@dataclass(frozen=True)
class Decision:
    """What to do after one layer.

    Attributes
    ----------
    action : str
        ``"none"``, ``"notify"``, ``"pause"`` or ``"cancel"``.
    reason : str
        One sentence for logs and notifications.
    layer : int
        Layer index the decision is about.
    """

    action: Action
    reason: str
    layer: int

    @property
    def stops(self) -> bool:
        """True for pause or cancel."""
        return self.action in ("pause", "cancel")


def _overlap(a: Sequence[float], b: Sequence[float]) -> bool:
    """Bounding boxes ``(x0, y0, x1, y1)`` overlap (touching counts)."""
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


class PausePolicy:
    """Stateful pause policy; feed it every layer's result in order.

    Parameters
    ----------
    settings : PolicySettings
        Thresholds and actions.
    """

    def __init__(self, settings: PolicySettings | None = None) -> None:
        self.settings = settings or PolicySettings()
        self._streak = 0
        self._prev_regions: list[Region] = []
        self._last_regions: list[Region] = []
        self._acked: list[tuple[tuple[float, ...], float]] = []
        self._halted = False
        self._last_ratio = 0.0
        self._acked_ratio = 0.0
        self._fresh_area = 0.0
        self._out_streak = 0
        self._prev_outside: list[Region] = []
        self._last_outside: list[Region] = []
        self._acked_outside: list[tuple[tuple[float, ...], float]] = []

    @property
    def halted(self) -> bool:
        """True after a pause/cancel decision until :meth:`acknowledge`."""
        return self._halted

    @property
    def acknowledged(self) -> list[tuple[tuple[float, ...], float]]:
        """Accepted regions as ``(bbox_mm (x0, y0, x1, y1), area_mm2)``; they count again only if they grow."""
        return list(self._acked)

    def acknowledge(self) -> None:
        """The operator resumed: forget the streak and accept the current regions."""
        for r in self._last_regions:
            self._acked.append((tuple(r.bbox_mm), float(r.area_mm2)))
        for r in self._last_outside:
            self._acked_outside.append((tuple(r.bbox_mm), float(r.area_mm2)))
        self._acked_ratio = max(self._acked_ratio, self._last_ratio)
        self._streak = self._out_streak = 0
        self._halted = False

    def _acked_area(self, r: Region) -> float | None:
        """Acknowledged area of the region ``r`` overlaps, or None."""
        areas = [a for box, a in self._acked if _overlap(box, tuple(r.bbox_mm))]
        return max(areas) if areas else None

    def _fresh(self, regions: list[Region]) -> list[Region]:
        g = self.settings.growth_ratio
        out = []
        for r in regions:
            acked = self._acked_area(r)
            if acked is None or r.area_mm2 > g * acked:
                out.append(r)
        return out

    def update(self, result: LayerResult) -> Decision:
        """Decide after one layer's result.

        Parameters
        ----------
        result : LayerResult
            The layer's analysis (``status`` ``"error"`` alerts only).

        Returns
        -------
        Decision
        """
        s = self.settings
        layer = int(result.layer)
        if result.status == "error":
            return Decision("notify", f"layer {layer} not analysed: {result.message or 'error'}", layer)
        if result.failed_check and result.status == "ok" and not self._halted:
            return self._stop(s.action, result.message or f"layer {layer}: check {result.failed_check} failed", layer)
        if result.status != "ok" or layer < s.skip_first_layers:
            return Decision("none", f"layer {layer} not judged ({result.status})", layer)
        regions = self._fresh(list(result.regions))
        ratio, outside = self._fresh_ratio(result, regions)
        prev, self._prev_regions = self._prev_regions, regions
        # after a resume, anomaly the operator accepted must grow before it counts again
        limit = max(s.pause_ratio, self._acked_ratio * s.growth_ratio)
        # a% of a small footprint jumps by a whole block at a time (1.44 mm^2 for the paper's grid): the ratio
        # rule also needs min_area_mm2 of fresh anomalous area, so two or three edge blocks never pause
        alarm = ratio > limit and self._fresh_area >= s.min_area_mm2
        self._streak = self._streak + 1 if alarm else 0
        outside_regions, outside_area = self._outside(result)
        if self._halted:
            return Decision("none", f"layer {layer}: already stopped, waiting for the operator", layer)
        if s.strong_outside_area_mm2 > 0 and outside > s.strong_outside_area_mm2:
            return self._stop(
                s.strong_action,
                f"layer {layer}: {outside:.0f} mm^2 of material outside the part "
                f"(> {s.strong_outside_area_mm2:.0f}; spaghetti or detachment?)",
                layer,
            )
        if self._out_streak >= s.consecutive_layers:
            big = outside_regions[0]
            return self._stop(s.action, f"layer {layer}: {outside_area:.0f} mm^2 changed beside the print "
                                        f"(largest at ({big.centroid_mm[0]:.0f}, {big.centroid_mm[1]:.0f}) mm) "
                                        f"for {self._out_streak} layers", layer)
        # a real failure stays in place: consecutive alarms must share a region
        # (isolated noise spikes land at random places); without regions, trust a%.
        persistent = not regions or not prev or any(
            _overlap(tuple(r.bbox_mm), tuple(p.bbox_mm)) for r in regions for p in prev
        )
        if self._streak >= s.consecutive_layers and persistent:
            return self._stop(s.action, f"layer {layer}: anomaly ratio {ratio:.1%} above {limit:.1%} "
                                        f"for {self._streak} layers", layer)
        grown = self._growth(regions, prev, layer)
        if grown is not None:
            return grown
        if self._out_streak and s.notify_single_layer and not alarm:
            return Decision("notify", f"layer {layer}: {outside_area:.0f} mm^2 changed beside the print", layer)
        if alarm and s.notify_single_layer:
            return Decision("notify", f"layer {layer}: anomaly ratio {ratio:.1%} above {limit:.1%}", layer)
        return Decision("none", f"layer {layer}: anomaly ratio {ratio:.1%}", layer)

    def _outside(self, result: LayerResult) -> tuple[list[Region], float]:
        """The outside rule's state after ``result``: fresh outside regions (largest first) and their area, mm^2.

        Regions the operator acknowledged count again only when they grew by ``growth_ratio``.
        """
        s = self.settings
        self._last_outside = list(result.outside_regions)
        fresh = []
        for r in result.outside_regions:
            acked = [a for box, a in self._acked_outside if _overlap(box, tuple(r.bbox_mm))]
            if not acked or r.area_mm2 > s.growth_ratio * max(acked):
                fresh.append(r)
        area = float(sum(r.area_mm2 for r in fresh))
        alarm = s.outside_pause_mm2 > 0 and area >= s.outside_pause_mm2
        prev, self._prev_outside = self._prev_outside, (fresh if alarm else [])
        same_place = not prev or any(_overlap(tuple(r.bbox_mm), tuple(p.bbox_mm)) for r in fresh for p in prev)
        self._out_streak = (self._out_streak + 1 if same_place else 1) if alarm else 0
        return fresh, area

    def _fresh_ratio(self, result: LayerResult, regions: list[Region]) -> tuple[float, float]:
        """a% and outside area of the anomaly the operator has not acknowledged (``regions`` are the fresh ones).

        Also remembers the fresh anomalous area (``_fresh_area``, mm^2) and the diffuse
        anomaly not explained by regions (``_last_ratio``, for :meth:`acknowledge`).
        """
        self._last_regions = list(result.regions)
        acked_area = sum(r.area_mm2 for r in result.regions if r not in regions)
        printed = result.printed_area_mm2
        self._fresh_area = max(result.anomalous_area_mm2 - acked_area, 0.0)
        if printed and printed > 0:
            ratio = self._fresh_area / printed
            self._last_ratio = max(result.anomalous_area_mm2 - sum(r.area_mm2 for r in result.regions), 0.0) / printed
        else:
            ratio = float(result.anomaly_ratio) if not self._acked else 0.0
            self._last_ratio = ratio
        outside = result.outside_area_mm2
        if self._acked and acked_area > 0:
            outside = min(outside, sum(r.area_mm2 * r.outside_fraction for r in regions))
        return ratio, outside

    def _growth(self, regions: list[Region], prev: list[Region], layer: int) -> Decision | None:
        """The growth rule: a region that outgrew its acknowledged area or its overlapping predecessor."""
        s = self.settings
        for r in regions:
            if r.area_mm2 < s.growth_min_area_mm2:
                continue
            where = f"({r.centroid_mm[0]:.0f}, {r.centroid_mm[1]:.0f}) mm"
            acked = self._acked_area(r)
            if acked is not None:  # _fresh kept it, so it outgrew its acknowledged size
                return self._stop(s.action, f"layer {layer}: acknowledged region at {where} "
                                            f"grew from {acked:.0f} to {r.area_mm2:.0f} mm^2", layer)
            for p in prev:
                if _overlap(tuple(r.bbox_mm), tuple(p.bbox_mm)) and r.area_mm2 >= s.growth_ratio * max(p.area_mm2, 1e-9):
                    return self._stop(s.action, f"layer {layer}: failing region at {where} "
                                                f"grew from {p.area_mm2:.0f} to {r.area_mm2:.0f} mm^2", layer)
        return None

    def _stop(self, action: Action, reason: str, layer: int) -> Decision:
        if action in ("pause", "cancel"):
            self._halted = True
        return Decision(action, reason, layer)


def first_stop(results: Iterable[LayerResult], settings: PolicySettings | None = None) -> Decision | None:
    """Feed ``results`` (in layer order) to a fresh :class:`PausePolicy`; the first pause/cancel, or ``None``.

    What a printer would have done with a finished series (``analyze`` on a
    folder of photos); the monitor and the demo feed the policy layer by layer.
    """
    policy = PausePolicy(settings)
    for res in results:
        decision = policy.update(res)
        if decision.stops:
            return decision
    return None
