"""When would the printer have been paused? (policy for offline runs and the demo).

Uses :class:`layerwatch.monitor.policy.PausePolicy` when that module exists;
otherwise a small local rule with the same settings: pause when a% exceeds
``pause_ratio`` on ``consecutive_layers`` consecutive analysed layers (the
first ``skip_first_layers`` layers are never judged; ``"error"``/``"skipped"``
layers neither count nor reset the run).
"""

from __future__ import annotations

from dataclasses import dataclass

from layerwatch.analysis.result import LayerResult
from layerwatch.monitor.settings import PolicySettings

__all__ = ["Decision", "LocalPausePolicy", "pause_policy"]


@dataclass(frozen=True)
class Decision:
    """``action`` is ``"continue"`` or the configured action (``"pause"``...); ``reason`` says why."""

    action: str
    reason: str = ""


class LocalPausePolicy:
    """a% above ``pause_ratio`` on ``consecutive_layers`` consecutive analysed layers."""

    source = "local rule"

    def __init__(self, settings: PolicySettings | None = None) -> None:
        self.settings = settings or PolicySettings()
        self.run = 0

    def update(self, result: LayerResult) -> Decision:
        st = self.settings
        if result.status != "ok" or result.layer < st.skip_first_layers:
            return Decision("continue", f"layer {result.layer} not judged ({result.status})")
        if result.anomaly_ratio > st.pause_ratio:
            self.run += 1
        else:
            self.run = 0
        if self.run >= st.consecutive_layers:
            return Decision(st.action, f"a% = {100 * result.anomaly_ratio:.1f} % > {100 * st.pause_ratio:.1f} % "
                                       f"on {self.run} consecutive layers")
        return Decision("continue", f"a% = {100 * result.anomaly_ratio:.1f} %")

    def acknowledge(self) -> None:
        self.run = 0


def pause_policy(settings: PolicySettings | None = None):
    """The monitor's PausePolicy if available, else :class:`LocalPausePolicy`.

    Returns an object with ``update(result) -> decision`` (``.action``, ``.reason``)
    and a ``source`` attribute naming which one it is.
    """
    try:
        from layerwatch.monitor.policy import PausePolicy
    except ImportError:
        return LocalPausePolicy(settings)
    pol = PausePolicy(settings or PolicySettings())
    try:
        pol.source = "monitor.policy.PausePolicy"
    except AttributeError:
        pass
    return pol


def decision_action(decision) -> str:
    """``decision.action`` as a lower-case string (enum or str)."""
    a = getattr(decision, "action", decision)
    return str(getattr(a, "value", a)).lower()
