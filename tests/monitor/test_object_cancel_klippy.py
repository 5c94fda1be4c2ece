"""Cancel only the failed object on a REAL Klippy behind a REAL Moonraker (issue 21).

A four-object plate labelled for Klipper (``EXCLUDE_OBJECT_DEFINE`` / ``_START`` / ``_END``, as
PrusaSlicer and Orca write it with "label objects: firmware-specific") is printed; a stand-in
analysis reports a detached part on object B from layer 3 on. The monitor's policy decides
``cancel_object`` (the detachment default), the executor sends ``EXCLUDE_OBJECT NAME=B`` through
Moonraker, and Klippy skips B's moves from then on while A, C and D print to the end.

What B, A, C, D really printed is read from Klippy itself: after each object's block the test macro
``LW_MARK`` stores the toolhead's commanded position, which stays where the previous object ended
when Klippy drops an excluded object's moves; the test extruder
(``klippy_extras/layerwatch_test_extruder.py``: Klippy has no MCU here, so no real extruder) adds
up the filament Klippy pushed, which must be exactly A, C, D on every layer and B up to its cancel.
"""

import re
import threading

import httpx
import numpy as np
import pytest
from moonraker_stack import MoonrakerStack, require_installed, running, until

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.gcode.objects import read_objects
from layerwatch.gcode.reader import read_toolpath
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.policy import PausePolicy, PolicySettings

pytestmark = [pytest.mark.moonraker, pytest.mark.slow, pytest.mark.xdist_group("servers")]

OBJECTS = {"A": (60.0, 60.0), "B": (100.0, 60.0), "C": (60.0, 100.0), "D": (100.0, 100.0)}
N_LAYERS, LAYER_H, ONSET = 12, 0.3, 3

EXTRA_CFG = """[exclude_object]

[layerwatch_test_extruder]

[gcode_macro LW_MARK]
variable_seen: ''
gcode:
  {% set pos = printer.toolhead.position %}
  {% set mark = params.OBJ ~ params.LAYER ~ '@' ~ (pos.x|round(1)) ~ '/' ~ (pos.y|round(1)) ~ ' ' %}
  SET_GCODE_VARIABLE MACRO=LW_MARK VARIABLE=seen VALUE="'{seen ~ mark}'"
"""


def plate_gcode() -> str:
    """Four 10 mm squares with infill, each in its EXCLUDE_OBJECT block, a layerwatch trigger per layer."""
    lines = ["G90", "M83"]
    for name, (cx, cy) in OBJECTS.items():
        lines.append(f"EXCLUDE_OBJECT_DEFINE NAME={name} CENTER={cx:.1f},{cy:.1f} "
                     f"POLYGON=[[{cx - 5},{cy - 5}],[{cx + 5},{cy - 5}],[{cx + 5},{cy + 5}],[{cx - 5},{cy + 5}]]")
    for i in range(N_LAYERS):
        z = LAYER_H * (i + 1)
        lines += [f"G1 Z{z:.3f} F600", "LAYERWATCH_TEST_LAYER_TIME SECONDS=0.5"]  # the layer's printing time
        for name, (cx, cy) in OBJECTS.items():
            sq = [(cx + 5, cy - 5), (cx + 5, cy + 5), (cx - 5, cy + 5), (cx - 5, cy - 5)]
            lines += [f"EXCLUDE_OBJECT_START NAME={name}", f"G0 X{cx - 5:.1f} Y{cy - 5:.1f} F6000"]
            lines += [f"G1 X{x:.1f} Y{y:.1f} E0.4 F1800" for x, y in sq]
            lines += [f"G1 X{cx + 4:.1f} Y{cy - 4 + k:.1f} E0.3" if k % 2 == 0 else
                      f"G1 X{cx - 4:.1f} Y{cy - 4 + k:.1f} E0.3" for k in range(9)]
            lines += [f"EXCLUDE_OBJECT_END NAME={name}", f"LW_MARK OBJ={name} LAYER={i}"]
        lines.append(f"LAYERWATCH_SNAPSHOT LAYER={i} Z={z:.3f}")
    lines.append("LAYERWATCH_TEST_LAYER_TIME SECONDS=0.5")  # the end G-code: the last photo is taken
    return "\n".join(lines) + "\n"


class _DetachedB:
    """Stand-in analysis: a detached part on object B from ``ONSET`` on (it stays there after the cancel)."""

    def __init__(self, toolpath):
        self.toolpath, self.seen, self.replaced = toolpath, [], []

    def process(self, photo, layer_index):
        self.seen.append(layer_index)
        bx, by = OBJECTS["B"]
        bad = layer_index >= ONSET
        regions = [Region(60.0, (bx - 4, by - 4, bx + 4, by + 4), (bx, by), 40, 0.3, 0.1, 0.6, "detachment", 0.8)]
        return LayerResult(layer=layer_index, z=LAYER_H * (layer_index + 1), anomaly_ratio=0.15 if bad else 0.0,
                           printed_area_mm2=400.0, anomalous_area_mm2=60.0 if bad else 0.0,
                           regions=regions if bad else [])

    def replace_toolpath(self, toolpath):
        self.toolpath = toolpath
        self.replaced.append(toolpath)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    require_installed()
    s = MoonrakerStack(tmp_path_factory.mktemp("object_cancel"), extra_cfg=EXTRA_CFG)
    with running(s):
        yield s


def _marks(stack) -> dict[str, dict[int, tuple[float, float]]]:
    seen = stack.query("gcode_macro LW_MARK")["gcode_macro LW_MARK"]["seen"]
    out: dict[str, dict[int, tuple[float, float]]] = {n: {} for n in OBJECTS}
    for name, layer, x, y in re.findall(r"([A-D])(\d+)@([-\d.]+)/([-\d.]+)", seen):
        out[name][int(layer)] = (float(x), float(y))
    return out


def _inside(name, xy):
    cx, cy = OBJECTS[name]
    return abs(xy[0] - cx) <= 5.01 and abs(xy[1] - cy) <= 5.01


def test_failure_on_one_object_cancels_exactly_that_object_on_a_real_klippy(stack):
    text = plate_gcode()
    tp = read_toolpath(text.encode())
    objects = read_objects(text.encode(), tp)
    assert objects.style == "exclude_object" and [o.klipper_name for o in objects.objects] == list(OBJECTS)
    printer = MoonrakerPrinter(stack.url)
    pipe = _DetachedB(tp)
    mon = Monitor(printer, SimCamera(lambda layer: np.full((48, 64, 3), layer % 256, np.uint8)), pipe,
                  PausePolicy(PolicySettings(consecutive_layers=2)), objects=objects)
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("report", mon.run(poll_s=0.05)), daemon=True)
    try:
        assert printer.wait_connected(15)
        stack.upload_and_print("lw_plate.gcode", text)
        t.start()
        until(lambda: stack.query("print_stats")["print_stats"]["state"] == "complete", 60, "the plate to finish")
        t.join(20)
        assert not t.is_alive() and out["report"].outcome == "done"
        excluded = stack.query("exclude_object")["exclude_object"]
        assert excluded["excluded_objects"] == ["B"]  # exactly that object, as Klippy reports it
        stops = [d for d in mon.report.decisions if d.stops]
        assert [d.action for d in stops] == ["cancel_object"], [(d.action, d.reason) for d in stops]
        decided = stops[0].layer
        assert decided == ONSET + 1  # two layers in a row (consecutive_layers=2)
        # later layers: the failure is still in the photo, and raises no alarm
        later = [r for r in mon.report.results if r.layer > decided]
        assert len(later) == N_LAYERS - 1 - decided and all(r.decision == "none" for r in later)
        marks = _marks(stack)
        for name in "ACD":  # the others print every layer
            assert sorted(marks[name]) == list(range(N_LAYERS)) and all(_inside(name, xy) for xy in marks[name].values())
        skipped = [i for i, xy in marks["B"].items() if not _inside("B", xy)]
        assert all(_inside("B", marks["B"][i]) for i in range(decided + 1))  # B printed up to the decision
        assert skipped == list(range(skipped[0], N_LAYERS)) and skipped[0] <= decided + 1, marks["B"]
        # the filament Klippy pushed: every layer of A, C, D and B's layers before the cancel, nothing more
        per_layer = 4 * 0.4 + 9 * 0.3
        extruded = stack.query("layerwatch_test_extruder")["layerwatch_test_extruder"]["extruded"]
        assert extruded == pytest.approx(per_layer * (3 * N_LAYERS + skipped[0]), abs=1e-3)
        print(f"\nKlippy: cancel decided after layer {decided}, B skipped from layer {skipped[0]}, "
              f"{extruded:.1f} mm filament pushed")
        # from the next layer the reference leaves B out
        b = objects.objects[1].index
        new = pipe.replaced[-1]
        later_lines = new.line[new.layers[decided + 1].seg_start:]
        assert not np.isin(later_lines, tp.line[objects.segment_object == b]).any()
        # the cause where the user looks: the printer's display and the console, through Moonraker's API
        msg = stack.query("display_status")["display_status"]["message"]
        assert msg == f"layerwatch: cancel object L{decided} detachment B", msg
        store = httpx.get(stack.url + "/server/gcode_store", params={"count": 200}, timeout=5).json()
        assert any("layerwatch: cancel object" in m["message"] for m in store["result"]["gcode_store"])
    finally:
        mon.stop_event.set()
        if t.is_alive():
            t.join(10)
        printer.close()
