"""The OctoPrint side of the plugin: mixins, events, hooks, API and UI (see the package notes)."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import flask
import octoprint.plugin
import octoprint.webcams
from octoprint.access.permissions import Permissions
from octoprint.events import Events
from octoprint.filemanager import FileDestinations

from layerwatch.analysis.result import LayerResult
from layerwatch.errors import ConfigError
from layerwatch.monitor.printers.base import parse_trigger

from .hold import SnapshotHold
from .job import HostActions, JobWatch
from .options import DEFAULTS, validate_options

_TAGS = {"source:plugin", "plugin:layerwatch"}
#: a% values kept for the tab's curve
_KEEP_RATIOS = 5000


class LayerwatchPlugin(
    octoprint.plugin.StartupPlugin,
    octoprint.plugin.SettingsPlugin,
    octoprint.plugin.TemplatePlugin,
    octoprint.plugin.AssetPlugin,
    octoprint.plugin.EventHandlerPlugin,
    octoprint.plugin.SimpleApiPlugin,
    octoprint.plugin.BlueprintPlugin,
):
    """The plugin (module notes)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._watch: JobWatch | None = None
        self._hold: SnapshotHold | None = None
        self._last_layer: int | None = None
        self._overlay: tuple[int, bytes] | None = None
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="layerwatch-job")
        self._settings_error: str | None = None
        self._state: dict[str, Any] = self._idle_state()

    @staticmethod
    def _idle_state() -> dict[str, Any]:
        return {"status": "idle", "job": None, "message": "", "layers": 0, "n_layers": 0, "pauses": 0,
                "alerts": 0, "last": None, "ratios": [], "stops": []}

    # ------------------------------------------------------------------ settings
    def get_settings_defaults(self) -> dict[str, Any]:
        return dict(DEFAULTS)

    def _current(self) -> dict[str, Any]:
        return {k: self._settings.get([k]) for k in DEFAULTS}

    def on_settings_save(self, data: dict[str, Any]) -> dict[str, Any] | None:
        """Store ``data`` only if the merged settings validate; else keep the old ones and report the error."""
        try:
            valid = validate_options({**self._current(), **data})
        except ConfigError as exc:
            self._settings_error = str(exc)
            self._logger.warning("settings not saved: %s", exc)
            self._push()
            return None
        self._settings_error = None
        self._push()
        return octoprint.plugin.SettingsPlugin.on_settings_save(self, {k: valid[k] for k in data})

    def on_after_startup(self) -> None:
        try:
            validate_options(self._current())
        except ConfigError as exc:
            self._settings_error = str(exc)
            self._logger.warning("layerwatch settings need attention: %s", exc)

    # ------------------------------------------------------------------ UI
    def get_template_configs(self) -> list[dict[str, Any]]:
        return [{"type": "tab", "name": "layerwatch", "custom_bindings": True},
                {"type": "settings", "name": "layerwatch", "custom_bindings": False}]

    def is_template_autoescaped(self) -> bool:
        return True  # the templates hold no Jinja values, only knockout bindings

    def get_assets(self) -> dict[str, list[str]]:
        return {"js": ["js/layerwatch.js"]}

    def is_api_protected(self) -> bool:
        return True

    def is_blueprint_protected(self) -> bool:
        return True

    def is_blueprint_csrf_protected(self) -> bool:
        return True

    def on_api_get(self, request):
        """``GET /api/plugin/layerwatch``: the watched job, every layer's a%, the holds and any settings error."""
        return flask.jsonify(self._public_state())

    @octoprint.plugin.BlueprintPlugin.route("/overlay.png", methods=["GET"])
    @Permissions.STATUS.require(403)
    def overlay_png(self):
        """The latest layer's overlay (heatmap and failing regions over the photo's top view)."""
        with self._lock:
            overlay = self._overlay
        if overlay is None:
            flask.abort(404)
        resp = flask.make_response(overlay[1])
        resp.headers["Content-Type"] = "image/png"
        resp.headers["Cache-Control"] = "no-store"
        return resp

    def _public_state(self) -> dict[str, Any]:
        with self._lock:
            state = {**self._state, "ratios": list(self._state["ratios"]), "stops": list(self._state["stops"])}
            hold = self._hold
        state["holds"] = hold.records() if hold is not None else []
        state["settings_error"] = self._settings_error
        state["overlay_layer"] = self._overlay[0] if self._overlay else None
        return state

    def _push(self) -> None:
        state = self._public_state()
        state["ratios"] = state["ratios"][-200:]
        self._plugin_manager.send_plugin_message(self._identifier, state)

    # ------------------------------------------------------------------ job
    def on_event(self, event: str, payload: dict[str, Any] | None) -> None:
        if event == Events.PRINT_STARTED:
            self._start_job(payload or {})
        elif event in (Events.PRINT_DONE, Events.PRINT_FAILED, Events.PRINT_CANCELLED):
            self._end_job({Events.PRINT_DONE: "done", Events.PRINT_FAILED: "failed"}.get(event, "cancelled"))
        elif event in (Events.PRINT_PAUSED, Events.PRINT_RESUMED) and self._watch is not None:
            with self._lock:
                self._state["status"] = "paused" if event == Events.PRINT_PAUSED else "watching"
            self._push()

    def _start_job(self, payload: dict[str, Any]) -> None:
        self._end_job("replaced")
        state = {**self._idle_state(), "job": payload.get("name")}
        try:
            options = validate_options(self._current())
        except ConfigError as exc:
            self._set_state({**state, "status": "error", "message": f"not watched: {exc}"})
            return
        if not options["enabled"]:
            self._set_state({**state, "message": "layerwatch is switched off in its settings"})
            return
        if payload.get("origin") != FileDestinations.LOCAL:
            self._set_state({**state, "status": "error", "message": "not watched: the job prints from the "
                             "printer's SD card, so OctoPrint cannot hold it for the photo; upload it to OctoPrint."})
            return
        path = self._file_manager.path_on_disk(FileDestinations.LOCAL, payload["path"])
        watch = JobWatch(options, path, HostActions(self._pause, self._cancel), self._snapshot, self._on_result)
        hold = SnapshotHold(lambda on: self._printer.set_job_on_hold(on, blocking=not on), watch.take,
                            options["hold_timeout_s"])
        with self._lock:
            self._watch, self._hold, self._last_layer, self._overlay = watch, hold, None, None
            self._state = {**state, "status": "starting"}
        self._worker.submit(self._setup, watch)

    def _setup(self, watch: JobWatch) -> None:
        watch.setup()
        with self._lock:
            if self._watch is not watch:
                return
            self._state["n_layers"] = watch.n_layers
            self._state["status"] = "error" if watch.error else "watching"
            self._state["message"] = f"not watched: {watch.error}" if watch.error else ""
        self._push()

    def _end_job(self, outcome: str) -> None:
        """The print ended: release any hold, then finish the analyses still queued before saying ``outcome``.

        Until they are done the status reads ``finishing`` (the last layer's photo is taken while the
        printer holds; its analysis may end after the print does), so ``done`` means every photo taken
        has been judged.
        """
        with self._lock:
            watch, hold = self._watch, self._hold
            self._watch = None
            if watch is not None and self._state["status"] != "error":
                self._state["status"] = "finishing"
        if hold is not None:
            hold.end()
        if watch is not None:
            self._worker.submit(self._finish, watch, outcome)
            self._push()

    def _finish(self, watch: JobWatch, outcome: str) -> None:
        """On the worker: wait for ``watch``'s queued analyses, then show the job's outcome."""
        try:
            watch.close()
        finally:
            with self._lock:
                current = self._watch is None and self._state["status"] == "finishing"
                if current:
                    self._state["status"] = outcome
            if current:
                self._push()

    def _set_state(self, state: dict[str, Any]) -> None:
        with self._lock:
            self._watch = self._hold = None
            self._state = state
        self._push()

    def _pause(self) -> None:
        self._printer.pause_print(tags=_TAGS)

    def _cancel(self) -> None:
        self._printer.cancel_print(tags=_TAGS)

    def _snapshot(self) -> bytes:
        """A JPEG from OctoPrint's snapshot webcam (its provider plugin takes it)."""
        webcam = octoprint.webcams.get_snapshot_webcam()
        if webcam is None or not webcam.config.canSnapshot:
            raise ConfigError("OctoPrint has no webcam that takes snapshots; set the snapshot URL in "
                              "Settings > Webcam, or a camera in the layerwatch settings.")
        return b"".join(webcam.providerPlugin.take_webcam_snapshot(webcam.config.name))

    def _on_result(self, res: LayerResult, png: bytes | None) -> None:
        last = {"layer": res.layer, "z": res.z, "status": res.status, "ratio_pct": round(100 * float(res.anomaly_ratio), 3),
                "decision": res.decision, "reason": res.decision_reason, "message": res.message}
        with self._lock:
            self._state["layers"] += 1
            self._state["last"] = last
            if res.decision in ("pause", "cancel"):
                self._state["pauses"] += 1
                self._state["stops"].append([res.layer, res.decision, res.decision_reason])
            self._state["alerts"] += int(res.status == "error" or res.decision not in ("none", None))
            ratios = self._state["ratios"]
            ratios.append([res.layer, last["ratio_pct"] if res.status == "ok" else None])
            del ratios[:-_KEEP_RATIOS]
            if png is not None:
                self._overlay = (res.layer, png)
        self._push()

    # ------------------------------------------------------------------ hooks (OctoPrint's comm threads)
    def on_atcommand_sending(self, comm, phase, command, parameters, tags=None, *args, **kwargs) -> None:
        """``@layerwatch snapshot layer=N z=Z`` reached the send loop: the head is parked (``M400`` acknowledged)."""
        if command == "layerwatch":
            self._on_trigger(f"layerwatch {parameters}")

    def on_gcode_sending(self, comm, phase, cmd, cmd_type, gcode, subcode=None, tags=None, *args, **kwargs):
        """``M118 ... layerwatch snapshot ...`` (profiles without the ``@`` line); never changes the line."""
        if gcode == "M118" and "layerwatch snapshot" in cmd:
            self._on_trigger(cmd)
        return None

    def _on_trigger(self, line: str) -> None:
        trigger = parse_trigger(line, "octoprint")
        if trigger is None:
            return
        with self._lock:
            hold = self._hold
            if self._watch is None or hold is None or trigger.layer == self._last_layer:
                return  # no job watched, or the M118 line of an @ trigger already handled
            self._last_layer = trigger.layer
        hold.trigger(trigger)
