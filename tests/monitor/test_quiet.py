"""Quiet when it should be (issue 21): start/end G-code layers and a macro's quiet signal are not judged,
and detection resumes by itself."""

import time

import numpy as np

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.gcode.objects import quiet_layers, read_objects
from layerwatch.gcode.reader import read_toolpath
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.base import (
    SnapshotTrigger,
    parse_line,
    parse_signal,
    parse_trigger,
)
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter
from layerwatch.monitor.printers.octoprint import parse_octoprint_message
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy


class Failing:
    """Stand-in analysis: every layer fails (a paused print would mean the layer was judged)."""

    def __init__(self):
        self.seen = []

    def process(self, photo, layer_index):
        self.seen.append(layer_index)
        return LayerResult(layer=layer_index, z=0.3 * (layer_index + 1), anomaly_ratio=0.5, printed_area_mm2=1000,
                           anomalous_area_mm2=500, regions=[Region(500, (90, 90, 110, 110), (100, 100), 40, 0.2)])


def _cam():
    return SimCamera(lambda layer: np.full((64, 64, 3), layer % 256, np.uint8))


def test_signals_are_parsed_from_every_host_format():
    q = parse_signal("M118 E1 layerwatch quiet s=300")
    assert (q.signal, q.z, q.layer) == ("quiet", 300.0, -1)
    assert parse_signal('RESPOND MSG="layerwatch quiet"').z == 600.0  # default
    assert parse_signal("M118 E1 layerwatch quiet s=99999").z == 3600.0  # capped: it always resumes
    assert parse_signal("echo:layerwatch watch").signal == "watch"
    assert parse_signal("; layerwatch quiet") is None and parse_signal("M117 hello") is None
    assert parse_signal("M118 E1 layerwatch snapshot layer=3 z=1.2") is None
    assert parse_trigger("M118 E1 layerwatch quiet") is None  # files with only signals have no triggers
    assert parse_line("M118 E1 layerwatch snapshot layer=3 z=1.2").layer == 3
    (t,) = parse_octoprint_message({"current": {"logs": ["Recv: echo:layerwatch quiet s=120"]}})
    assert t.signal == "quiet" and t.z == 120
    mr = MoonrakerPrinter("http://127.0.0.1:9", push=False)
    mr.handle_frame({"method": "notify_gcode_response", "params": ["// layerwatch quiet s=60", "// layerwatch watch"]})
    assert [(t.signal, t.z) for t in mr.poll_triggers()] == [("quiet", 60.0), ("watch", 0.0)]
    mr.close()


def test_queue_script_signal_suspends_detection_until_watch():
    lines = []
    for i in range(12):
        lines += [f"G1 Z{0.3 * (i + 1):.2f}", f"M118 E1 layerwatch snapshot layer={i} z={0.3 * (i + 1):.3f}"]
        if i == 1:
            lines.append("M118 E1 layerwatch quiet s=600")  # e.g. a farm queue's bed-clearing script
        if i == 7:
            lines.append("M118 E1 layerwatch watch")
    vp = VirtualPrinter("\n".join(lines).encode())
    pipe = Failing()
    mon = Monitor(vp, _cam(), pipe, PausePolicy())
    rep = mon.run(poll_s=0.001)
    skipped = [r.layer for r in rep.results if r.status == "skipped"]
    assert skipped == [2, 3, 4, 5, 6, 7] and all("quiet" in r.message for r in rep.results if r.status == "skipped")
    assert pipe.seen[:2] == [0, 1] and 8 in pipe.seen  # judged again after the watch signal
    stop = next(d for d in rep.decisions if d.stops)
    assert stop.layer == 9  # layers 8 and 9 in a row (layers 0, 1 are skip_first_layers / a single alarm)


def test_quiet_signal_runs_out_by_itself():
    mon = Monitor(VirtualPrinter(b"G1 X0\n"), _cam(), Failing(), PausePolicy(), wait_for_verdict=True)
    mon.handle_trigger(SnapshotTrigger(-1, 0.3, "virtual", signal="quiet"))
    assert mon.handle_trigger(SnapshotTrigger(2, 0.9, "virtual")).status == "skipped"
    time.sleep(0.35)
    assert mon.handle_trigger(SnapshotTrigger(3, 1.2, "virtual")).status == "ok"


def test_start_and_end_gcode_layers_are_quiet(tmp_path):
    start = ["G90", "M83", "G1 Z5 F600", "G1 X5 Y5 E4 F600", "G1 X30 Y5 E4"]  # a purge at Z 5: the start G-code
    body = []
    for i in range(4):
        z = 0.2 * (i + 1)
        body += [f"G1 Z{z:.2f}", "EXCLUDE_OBJECT_START NAME=P", "G1 X50 Y50", "G1 X60 Y50 E0.5", "G1 X60 Y60 E0.5",
                 "EXCLUDE_OBJECT_END NAME=P"]
    end = ["G1 Z12", "G1 X5 Y150 E3"]  # a prime blob on the way out: the end G-code
    tp = read_toolpath(("\n".join(start + body + end) + "\n").encode())
    om = read_objects(("\n".join(start + body + end) + "\n").encode(), tp)
    zs = [round(lay.z, 2) for lay in tp.layers]
    quiet = quiet_layers(tp, om)
    assert {zs[i] for i in quiet} == {5.0, 12.0} and len(quiet) == 2, zs
    # unlabelled: skirt / purge features only
    assert quiet_layers(tp) == frozenset()  # no feature tags: every extrusion counts as part
    mon = Monitor(VirtualPrinter(b"G1 X0\n"), _cam(), Failing(), PausePolicy(), wait_for_verdict=True,
                  quiet_layers=quiet)
    q = sorted(quiet)[0]
    res = mon.handle_trigger(SnapshotTrigger(q, tp.layers[q].z, "virtual"))
    assert res.status == "skipped" and "start/end G-code" in res.message and res.decision == "none"
