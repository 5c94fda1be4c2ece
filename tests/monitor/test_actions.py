"""Carrying out decisions (issue 21): cancel one object or pause and say why, host commands, the audit log."""

import os
from pathlib import Path

import pytest

from layerwatch.analysis.result import Region
from layerwatch.gcode.objects import read_objects
from layerwatch.gcode.reader import read_toolpath
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.pipeline.actions import ActionExecutor, host_message
from layerwatch.pipeline.policy import Decision, PausePolicy
from layerwatch.storage.history import History

SHARED_DATA = Path(os.environ.get("LAYERWATCH_SHARED_DATA", Path(__file__).resolve().parents[2].parent / "shared" / "data"))


class _Pipe:
    """What the executor needs of a LayerPipeline: its toolpath and replace_toolpath."""

    def __init__(self, tp):
        self.toolpath = tp
        self.replaced = []

    def replace_toolpath(self, tp):
        self.toolpath = tp
        self.replaced.append(tp)


def _job(name):
    path = SHARED_DATA / "gcode" / name
    if not path.is_file():
        pytest.skip("shared data absent")
    tp = read_toolpath(path)
    return tp, read_objects(path, tp)


def _on(obj, h=1.5):
    cx, cy = obj.center_mm
    return Region(9.0, (cx - h, cy - h, cx + h, cy + h), (cx, cy), 3, 0.2, 0.0, 0.0, "detachment")


def _setup(tmp_path, name):
    tp, om = _job(name)
    prn = VirtualPrinter(b"G1 X0\n")
    h = History(tmp_path / "h.db")
    job = h.start_job("virtual", name)
    pipe = _Pipe(tp)
    return tp, om, prn, h, ActionExecutor(prn, om, pipe, h, job), pipe


def test_cancel_one_object_on_an_m486_plate(tmp_path):
    tp, om, prn, h, ex, pipe = _setup(tmp_path, "prusaslicer-2.4.0a1_m486_arcwelder.gcode")
    target = om.objects[2]
    policy = PausePolicy()
    d = Decision("cancel_object", "layer 9: detached", 9, "detachment", (_on(target),))
    done = ex.execute(d, policy)
    assert done.ok and done.target == target and done.decision.action == "cancel_object"
    assert prn.cancelled_objects == [target.name] and f"M486 P{target.firmware_id}" in prn.sent
    assert prn.status().state == "printing"  # the other objects go on
    assert any(s.startswith("M117 layerwatch: cancel object L9 detachment") for s in prn.sent)
    # from layer 10 the reference has no segment of the object; up to layer 9 it keeps them
    new = pipe.replaced[-1]
    for i in (9, 10, tp.n_layers - 1):
        lines = set(new.line[new.layer_slice(i)].tolist())
        mine = set(tp.line[tp.layer_slice(i)][om.segment_object[tp.layer_slice(i)] == target.index].tolist())
        assert (mine <= lines) if i <= 9 else not (mine & lines), i
    assert policy.ignored_zones and policy.ignored_zones[0][1] == target.name
    (row,) = h.audit()
    assert (row["action"], row["actor"]) == ("cancel object", "layerwatch")
    assert row["detail"]["object"] == target.name and row["detail"]["layer"] == 9
    h.close()


@pytest.mark.parametrize("where", ["spans", "none"])
def test_cancel_object_falls_back_to_pause_and_says_why(tmp_path, where):
    tp, om, prn, h, ex, _ = _setup(tmp_path, "prusaslicer-2.4.0a1_m486_arcwelder.gcode")
    a, b = om.objects[1], om.objects[2]  # side by side, y 153..158
    region = (Region(80, (min(a.bbox_mm[0], b.bbox_mm[0]) - 2, 154, max(a.bbox_mm[2], b.bbox_mm[2]) + 2, 157),
                     (145, 155), 9, 0.2) if where == "spans"
              else Region(9, (20, 20, 23, 23), (21, 21), 2, 0.2))
    done = ex.execute(Decision("cancel_object", "layer 5: x", 5, "detachment", (region,)), PausePolicy())
    assert done.decision.action == "pause" and prn.status().state == "paused" and not prn.cancelled_objects
    assert ("spans 2 objects" if where == "spans" else "touches no object") in done.decision.reason
    assert "paused instead" in done.decision.reason and h.audit()[0]["action"] == "pause"
    h.close()


def test_comment_labels_only_the_firmware_cannot_skip_so_it_pauses(tmp_path):
    _, om, prn, h, ex, _ = _setup(tmp_path, "slic3r-1.3.1-dev_multi-object.gcode")
    done = ex.execute(Decision("cancel_object", "layer 5: x", 5, "detachment", (_on(om.objects[0]),)), PausePolicy())
    assert done.decision.action == "pause" and prn.status().state == "paused"
    assert "could not cancel" in done.decision.reason and "no firmware labels" in done.decision.reason
    h.close()


def test_file_without_labels_pauses(tmp_path):
    _, om, prn, h, ex, _ = _setup(tmp_path, "prusaslicer-2.6.0_mini-ascii.gcode")
    done = ex.execute(Decision("cancel_object", "layer 5: x", 5, "detachment", (_on(om.objects[0]),)), PausePolicy())
    assert done.decision.action == "pause" and "labels no objects" in done.decision.reason
    h.close()


def test_host_command_and_cancel_and_failures_are_audited(tmp_path):
    _, om, prn, h, ex, _ = _setup(tmp_path, "prusaslicer-2.6.0_mini-ascii.gcode")
    assert ex.execute(Decision("host_command", "layer 3: spaghetti", 3, "spaghetti", (), "COOL_DOWN")).ok
    assert "COOL_DOWN" in prn.sent
    assert ex.execute(Decision("cancel", "layer 4: x", 4, "unknown")).ok and prn.status().state == "cancelled"

    class Dead(VirtualPrinter):
        def pause(self):
            raise OSError("host gone")

    dead = ActionExecutor(Dead(b"G1 X0\n"), history=h, job_id=1)
    done = dead.execute(Decision("pause", "layer 5: x", 5, "unknown"))
    assert not done.ok and "host gone" in done.error
    rows = h.audit()
    assert [r["action"] for r in rows] == ["pause", "cancel", "host command"]
    assert rows[0]["detail"]["ok"] is False and rows[2]["detail"]["command"] == "COOL_DOWN"
    h.close()


def test_resume_at_the_printer_is_audited_with_its_source(tmp_path):
    _, _, prn, h, ex, _ = _setup(tmp_path, "prusaslicer-2.6.0_mini-ascii.gcode")
    ex.execute(Decision("pause", "layer 5: x", 5, "unknown"))
    ex.state_changed("printing", "paused")  # the pause layerwatch sent: audited once, by layerwatch
    ex.state_changed("paused", "printing")  # resumed by someone at the printer
    ex.state_changed("printing", "paused")  # paused from the host's UI
    rows = h.audit()
    assert [(r["action"], r["actor"]) for r in rows] == [("pause", "printer"), ("resume", "printer"),
                                                         ("pause", "layerwatch")]
    h.close()


def test_host_message_is_safe_for_a_gcode_line():
    msg = host_message(Decision("cancel_object", "r", 12, "detachment"), 'cube;"M84"')
    assert msg == "layerwatch: cancel object L12 detachment cube__M84_" and len(msg) <= 64
