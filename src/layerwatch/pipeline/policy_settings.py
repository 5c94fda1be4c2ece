"""The pause policy's settings: ``[policy]``, ``[policy.kinds.<kind>]`` and ``[notify]``.

:class:`PolicySettings` holds the thresholds of the rules that
:class:`~layerwatch.pipeline.policy.PausePolicy` applies (its module notes
list the rules), :class:`KindActions` what each failure kind
(:mod:`layerwatch.analysis.failure_kinds`) does when a rule fires, and
:class:`NotifySettings` where alerts go. Validated at the edge: a value out of
range fails when the configuration is read, with the key's name.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from layerwatch.analysis.failure_kinds import FAILURE_KINDS, UNKNOWN
from layerwatch.settings_base import Section

__all__ = ["Action", "DEFAULT_KIND_ACTIONS", "KindAction", "KindActionName", "KindActions", "NotifySettings",
           "PolicySettings", "STOPPING"]

Action = Literal["none", "notify", "pause", "cancel", "cancel_object", "host_command"]
#: what a failure kind may do; ``"rule"``: what the rule that fired says (``action`` / ``strong_action``)
KindActionName = Literal["rule", "notify", "pause", "cancel", "cancel_object", "host_command"]
#: actions that stop (or take over) the job; the policy then waits for the operator
STOPPING = frozenset({"pause", "cancel", "cancel_object", "host_command"})
#: the documented per-kind defaults: a detached part of a multi-object plate is cancelled alone (a pause
#: when the G-code does not label its objects or the failure spans several); every other kind does what
#: the rule says (pause by default): a wrongly typed region must still stop the print
DEFAULT_KIND_ACTIONS: dict[str, dict[str, object]] = {k: {"action": "rule"} for k in FAILURE_KINDS}
DEFAULT_KIND_ACTIONS["detachment"] = {"action": "cancel_object"}
_MAX_COMMAND = 200


class KindAction(Section):
    """What one failure kind does (config table ``[policy.kinds.<kind>]``).

    Attributes
    ----------
    action : {"rule", "notify", "pause", "cancel", "cancel_object", "host_command"}
        ``"rule"``: the firing rule's ``action``/``strong_action``; ``"cancel_object"``: cancel only the
        object the failing region lies on (:mod:`layerwatch.pipeline.actions`; a pause when it cannot);
        ``"host_command"``: send ``command`` to the host (e.g. a Klipper macro that cools down), then wait
        for the operator like after a pause.
    warn_mm2 : float
        Fresh area of this kind on one layer that sends a notification, mm^2 (0: the rules' notification).
    act_mm2 : float
        Fresh area of this kind on ``consecutive_layers`` layers in a row, in overlapping places, that takes
        ``action``, mm^2. 0: the general rules decide; above 0 it replaces them for regions of this kind
        (larger: less sensitive, smaller: more).
    command : str
        The host command of ``"host_command"``: one G-code line or macro call, printable ASCII.
    """

    action: KindActionName = "rule"
    warn_mm2: float = Field(0.0, ge=0)
    act_mm2: float = Field(0.0, ge=0)
    command: str = ""

    @field_validator("command")
    @classmethod
    def _one_line(cls, v: str) -> str:
        v = v.strip()
        if len(v) > _MAX_COMMAND or any(not (32 <= ord(c) < 127) for c in v):
            raise ValueError(f"command must be one line of printable ASCII, at most {_MAX_COMMAND} characters")
        return v

    @model_validator(mode="after")
    def _command_given(self) -> KindAction:
        if self.action == "host_command" and not self.command:
            raise ValueError('action "host_command" needs a command, e.g. command = "COOL_DOWN"')
        return self


def _kind_field(kind: str):
    return Field(default_factory=lambda: KindAction(**DEFAULT_KIND_ACTIONS[kind]))


class KindActions(Section):
    """Per failure kind, its :class:`KindAction` (``[policy.kinds.<kind>]``); defaults in :data:`DEFAULT_KIND_ACTIONS`.

    A table that sets some keys of a kind keeps that kind's defaults for the others.
    """

    spaghetti: KindAction = _kind_field("spaghetti")
    foreign_body: KindAction = _kind_field("foreign_body")
    detachment: KindAction = _kind_field("detachment")
    layer_shift: KindAction = _kind_field("layer_shift")
    infill_defect: KindAction = _kind_field("infill_defect")
    thin_wall: KindAction = _kind_field("thin_wall")
    nothing_extruded: KindAction = _kind_field("nothing_extruded")
    unknown: KindAction = _kind_field("unknown")

    @model_validator(mode="before")
    @classmethod
    def _over_defaults(cls, data: object) -> object:
        if not isinstance(data, dict):
            return data
        return {k: ({**DEFAULT_KIND_ACTIONS[k], **v} if k in DEFAULT_KIND_ACTIONS and isinstance(v, dict) else v)
                for k, v in data.items()}

    def of(self, kind: str) -> KindAction:
        """The settings of ``kind`` (an untyped ``""`` or unknown name: ``"unknown"``'s)."""
        return getattr(self, kind if kind in FAILURE_KINDS else UNKNOWN)


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
        Fresh anomalous area the ratio rule also needs, mm^2: the anomalous blocks' whole
        tiles, whatever S_A counts of them (a small footprint crosses any ratio with two
        or three 1.44 mm^2 blocks; :func:`layer_alarm`).
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
    resume_grace_layers : int
        Analysed layers after a resume in which only an acknowledged region that grew by
        ``growth_ratio``, or a failing region in a new place, stops the print again: anomaly
        without a region (a%) and change beside the print do not (the operator just touched
        the printer). Acknowledged regions stay accepted after it, unless they grow.
    kinds : KindActions
        Action and thresholds per failure kind (``[policy.kinds.<kind>]``).
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
    resume_grace_layers: int = Field(3, ge=0)
    kinds: KindActions = Field(default_factory=KindActions)


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
