"""Carry out the pause policy's decisions on the printer: pause, cancel, cancel one object, a host command.

:class:`ActionExecutor` is what the monitor calls for a stopping
:class:`~layerwatch.pipeline.policy.Decision`:

* ``"pause"`` / ``"cancel"``: the host's pause / cancel;
* ``"host_command"``: the kind's ``command`` line (a Klipper macro, a G-code line) through the host;
* ``"cancel_object"``: the failing regions are mapped to the plate's objects
  (:meth:`~layerwatch.gcode.objects.ObjectMap.locate`); exactly one object touched is
  cancelled through the host (Klipper ``EXCLUDE_OBJECT NAME=..``; Marlin/Prusa ``M486 P<id>``,
  also through OctoPrint, which has no object-cancel API of its own); from the next
  layer the pipeline's reference and footprint leave it out and the policy no longer
  judges its area nor its remains beside it, unless they reach an object still printed
  (:meth:`~layerwatch.pipeline.policy.PausePolicy.ignore_zone`). A failure that spans
  objects, touches none, a file without labels or a host that cannot skip objects falls
  back to a pause, and the reason says why.

Each action is shown where the user looks (the host's display and console:
:meth:`~layerwatch.monitor.printers.base.Printer.show_message`) and written to the
history's audit log with the source ``layerwatch`` (the dashboard writes its own).
A failing host call never raises here: the result says what happened.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

from layerwatch.errors import LayerwatchError
from layerwatch.gcode.objects import ObjectMap, PrintObject, without_objects
from layerwatch.pipeline.policy import Decision, PausePolicy

__all__ = ["ActionExecutor", "Executed", "host_message", "ZONE_MARGIN_MM"]

log = logging.getLogger("layerwatch.actions")

#: margin around a cancelled object's box that the policy stops judging, mm (its failure may spill over)
ZONE_MARGIN_MM = 2.0
_UNSAFE = re.compile(r"[^A-Za-z0-9 .,:()%+/_-]")


def host_message(decision: Decision, target: str = "") -> str:
    """One short line for the printer's display and the host console (printable ASCII, no ``;`` or quotes).

    ``"layerwatch: pause L12 spaghetti"``; ``target``: the cancelled object's name.
    """
    what = decision.action.replace("_", " ")
    text = f"layerwatch: {what} L{decision.layer}" + (f" {decision.kind}" if decision.kind else "") + \
        (f" {target}" if target else "")
    return _UNSAFE.sub("_", text)[:64]


@dataclass(frozen=True)
class Executed:
    """What was done for one decision.

    Attributes
    ----------
    decision : Decision
        The decision as carried out (a ``cancel_object`` that could not be done becomes a
        ``pause`` whose reason says why).
    ok : bool
        The host accepted the action.
    error : str
        The host's refusal, when not ``ok``.
    target : PrintObject or None
        The object cancelled.
    """

    decision: Decision
    ok: bool = True
    error: str = ""
    target: PrintObject | None = None


@dataclass
class ActionExecutor:
    """Carries out decisions on one job's printer.

    Parameters
    ----------
    printer : Printer
        The host connector.
    objects : ObjectMap, optional
        The job's labelled objects (:func:`~layerwatch.gcode.objects.read_objects`); without
        it, ``cancel_object`` pauses.
    pipeline : LayerPipeline, optional
        Its reference and footprint drop a cancelled object (``toolpath`` / ``replace_toolpath``).
    history, job_id : optional
        Where the audit log is written.
    """

    printer: Any
    objects: ObjectMap | None = None
    pipeline: Any = None
    history: Any = None
    job_id: int | None = None
    cancelled: dict[int, int] = field(default_factory=dict)  # object index -> layer it was cancelled after
    _full_toolpath: Any = None
    _last_sent: str = ""  # the state change layerwatch itself asked for last (not audited twice)

    def execute(self, decision: Decision, policy: PausePolicy | None = None) -> Executed:
        """Carry out ``decision`` (a stopping one); show it on the host and audit it.

        Parameters
        ----------
        decision : Decision
        policy : PausePolicy, optional
            Told to ignore a cancelled object's area (:meth:`~PausePolicy.ignore_zone`).
        """
        target = None
        if decision.action == "cancel_object":
            decision, target = self._choose_object(decision)
        try:
            self._send(decision, target)
            done = Executed(decision, target=target)
        except Exception as exc:  # noqa: BLE001 - a host fault or a connector bug: reported, never raised
            if target is None:
                done = Executed(decision, ok=False, error=str(exc))
            else:  # the host could not skip the object: pause instead
                fallback = replace(decision, action="pause",
                                   reason=f"{decision.reason}; could not cancel {target.name} ({exc}): paused instead")
                done = self._pause(fallback)
                target = None
        if done.ok and target is not None:
            self._forget_object(target, decision.layer, policy)
        self._last_sent = {"pause": "pause", "cancel": "cancel"}.get(done.decision.action, "") if done.ok else ""
        self._show(done.decision, target)
        self._audit(done)
        return done

    def _pause(self, decision: Decision) -> Executed:
        try:
            self.printer.pause()
            return Executed(decision)
        except Exception as exc:  # noqa: BLE001 - as in execute
            return Executed(decision, ok=False, error=str(exc))

    def state_changed(self, before: str, after: str) -> None:
        """Audit a pause, resume or cancel the monitor saw but did not send (source ``printer``: its
        display, the host's UI or a macro), unless the dashboard did it (it audits its own)."""
        action = {"paused": "pause", "cancelled": "cancel"}.get(after, "resume" if before == "paused" else "")
        if not action or self.history is None or action == self._last_sent:
            self._last_sent = ""
            return
        try:
            recent = self.history.audit(limit=20)
            if any(a["action"] == action and a["actor"] != "layerwatch" and time.time() - a["time"] < 30
                   for a in recent):
                return  # the dashboard's own row says who
            self.history.add_audit(action, "printer", "printer", None if self.job_id is None else f"job {self.job_id}",
                                   {"state": after, "source": "printer (its display, the host's UI or a macro)"})
        except LayerwatchError as exc:
            log.warning("audit log write failed: %s", exc)

    def _choose_object(self, decision: Decision) -> tuple[Decision, PrintObject | None]:
        """The one object ``decision``'s regions lie on, or a pause decision that says why not."""
        why = "the job's G-code was not read for objects"
        if self.objects is not None and self.pipeline is not None:
            tp = self._full_toolpath if self._full_toolpath is not None else self.pipeline.toolpath
            located = self.objects.locate(tp, decision.regions, decision.layer)
            if located.single is not None:
                return decision, self.objects.objects[located.single]
            why = located.reason
        elif self.objects is not None and not self.objects.labelled:
            why = "the G-code labels no objects (slice with label objects on)"
        return replace(decision, action="pause", reason=f"{decision.reason}; no object cancelled: {why}; "
                                                        "paused instead"), None

    def _send(self, decision: Decision, target: PrintObject | None) -> None:
        action = decision.action
        if action == "pause":
            self.printer.pause()
        elif action == "cancel":
            self.printer.cancel()
        elif action == "host_command":
            self.printer.send_gcode(decision.command)
        elif action == "cancel_object" and target is not None:
            self.printer.cancel_object(target)
        else:
            raise ValueError(f"not an action to carry out: {action}")

    def _forget_object(self, target: PrintObject, layer: int, policy: PausePolicy | None) -> None:
        """From the next layer: the reference and footprint leave ``target`` out; the policy ignores its area."""
        self.cancelled[target.index] = layer
        if policy is not None:
            x0, y0, x1, y1 = target.bbox_mm
            m = ZONE_MARGIN_MM
            others = [(o.bbox_mm[0] - m, o.bbox_mm[1] - m, o.bbox_mm[2] + m, o.bbox_mm[3] + m)
                      for o in (self.objects.objects if self.objects is not None else ())
                      if o.index not in self.cancelled]
            policy.ignore_zone((x0 - m, y0 - m, x1 + m, y1 + m), target.name, others)
        if self.pipeline is None or self.objects is None:
            return
        if self._full_toolpath is None:
            self._full_toolpath = self.pipeline.toolpath
        self.pipeline.replace_toolpath(without_objects(self._full_toolpath, self.objects, self.cancelled))

    def _show(self, decision: Decision, target: PrintObject | None) -> None:
        show: Callable[[str], None] | None = getattr(self.printer, "show_message", None)
        if show is None:
            return
        try:
            show(host_message(decision, target.name if target else ""))
        except Exception as exc:  # noqa: BLE001 - a message on the display never matters more than the print
            log.warning("could not show the action on the printer: %s", exc)

    def _audit(self, done: Executed) -> None:
        d = done.decision
        if self.history is None:
            return
        detail = {"layer": d.layer, "kind": d.kind, "reason": d.reason, "ok": done.ok}
        if done.error:
            detail["error"] = done.error
        if done.target is not None:
            detail["object"] = done.target.name
        if d.command:
            detail["command"] = d.command
        try:
            self.history.add_audit(d.action.replace("_", " "), "layerwatch", "layerwatch",
                                   None if self.job_id is None else f"job {self.job_id}", detail)
        except LayerwatchError as exc:
            log.warning("audit log write failed: %s", exc)
