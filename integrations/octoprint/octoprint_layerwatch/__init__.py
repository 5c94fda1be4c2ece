"""layerwatch for OctoPrint: a photo per layer, held still for it, analysed, paused on a failure.

The plugin (identifier ``layerwatch``) ties OctoPrint's parts to layerwatch's:

* **Job**: when a print of a local file starts (``PrintStarted``), the file is
  read from OctoPrint's file manager (``path_on_disk``) and a
  :class:`~octoprint_layerwatch.job.JobWatch` builds layerwatch's per-layer
  pipeline for it on a worker thread.
* **Trigger and hold**: the prepared file's ``@layerwatch snapshot layer=N z=Z``
  (``layerwatch gcode prepare --profile octoprint``; an ``M118 ... layerwatch
  snapshot ...`` line of the other profiles works too) reaches the
  ``octoprint.comm.protocol.atcommand.sending`` (or ``gcode.sending``) hook
  once the head is parked; :class:`~octoprint_layerwatch.hold.SnapshotHold` puts
  the job on hold (``set_job_on_hold``) until the frame is taken, at most
  ``hold_timeout_s``.
* **Camera**: OctoPrint's snapshot webcam (its webcam provider, e.g. the
  Classic Webcam's snapshot URL), or a layerwatch camera set in the settings.
* **Verdict**: layerwatch's monitor runs the analysis on its own worker thread
  and pauses (or cancels) through OctoPrint when the pause policy says so; a
  camera fault is an alert, never a pause.
* **UI**: a tab with the latest overlay and the a% of every layer, and a settings
  page (camera model, bed photo, job file, thresholds; validated on save).
"""

__plugin_name__ = "layerwatch"
__plugin_pythoncompat__ = ">=3.11,<4"


def __plugin_load__() -> None:
    """OctoPrint's entry point: create the plugin and register its hooks."""
    # imported here, not at the top: only OctoPrint has flask/octoprint, and the helpers
    # (hold, options, job) are imported and tested without them
    from .plugin import LayerwatchPlugin

    global __plugin_implementation__, __plugin_hooks__
    __plugin_implementation__ = LayerwatchPlugin()
    __plugin_hooks__ = {
        "octoprint.comm.protocol.atcommand.sending": __plugin_implementation__.on_atcommand_sending,
        "octoprint.comm.protocol.gcode.sending": __plugin_implementation__.on_gcode_sending,
    }
