"""The failure kinds a failing region can be typed as, shared by typing, policy, reports and the simulator.

A region's kind (:attr:`layerwatch.analysis.result.Region.kind`) names what
failed there; the pause policy chooses its action per kind, the reports count
by kind, and the evaluation builds its confusion matrix over these names. The
first six are the paper's failure types (and the simulator's
:data:`layerwatch.simulate.FAILURE_TYPES`); ``"nothing_extruded"`` is a layer
on which the G-code adds plastic and the photo shows none (clog, run-out);
``"unknown"`` is a region that no rule could type.
"""

from __future__ import annotations

__all__ = ["FAILURE_KINDS", "MOVED_KINDS", "UNKNOWN", "check_kind"]

#: Every kind a region can carry, in report order.
FAILURE_KINDS: tuple[str, ...] = (
    "spaghetti",
    "foreign_body",
    "detachment",
    "layer_shift",
    "infill_defect",
    "thin_wall",
    "nothing_extruded",
    "unknown",
)
UNKNOWN = "unknown"
#: Kinds of a part that moved: their regions report its displacement and its moved area.
MOVED_KINDS: tuple[str, ...] = ("layer_shift", "detachment")


def check_kind(kind: str) -> str:
    """Return ``kind`` when it is one of :data:`FAILURE_KINDS`.

    Raises
    ------
    ValueError
        Naming the known kinds, for a kind that is not one of them.
    """
    if kind not in FAILURE_KINDS:
        raise ValueError(f"unknown failure kind {kind!r}; use one of {', '.join(FAILURE_KINDS)}")
    return kind
