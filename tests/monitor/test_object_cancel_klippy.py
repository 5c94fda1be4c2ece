"""Cancel only the failed object on a REAL Klippy behind a REAL Moonraker (issue 21), decided by detection.

The plate of ``layerwatch demo --plate`` (four half-size copies of the bundled part, labelled for
Klipper with ``EXCLUDE_OBJECT_DEFINE`` / ``_START`` / ``_END``, its first ``N_LAYERS`` layers) is
printed by Klippy; every layer's photo is simulated (:class:`~layerwatch.simulate.PrintSimulator`)
with object B coming off the bed from layer ``ONSET`` (``Failure.within_mm``: B alone moves, by
``MOVE_MM`` away from A and D, so its evidence stays in B's zone: remains that reach another object
fall back to a pause, tests/evaluate/test_object_cancel.py) and judged by the recommended per-layer
pipeline (:class:`~layerwatch.pipeline.step.LayerPipeline`, markers located in the first photo as a
user's calibration would) and pause policy, every kind's action ``cancel_object`` as in the plate
demo (region typing may call a detached part another kind). The policy decides ``cancel_object``
from the detected regions, the executor maps them to B and sends ``EXCLUDE_OBJECT NAME=PART_B``
through Moonraker, and Klippy skips B's moves from then on while A, C and D print to the end.

The photos are simulated before the print starts (the camera answers at once, whatever the machine's
load): B as printed to the end, and B left out after each layer the cancel may follow (``CUTS``);
the camera picks the one that matches what Klippy printed (once Klippy reports B excluded, B's
layers after the last one it printed, by its ``LW_MARK``, are left out of the photos).

A real layer outlasts its analysis (seconds against tens of seconds); Klippy here prints a layer in
``LAYER_S``, so each layer also waits, in short ``LW_JUDGED`` steps that Moonraker's requests get in
between (as the ``klipper`` profile's hold does), until the monitor has judged and acted on the
layer before it: on a loaded machine the verdict still reaches Klippy before the next layer, as on
a printer. The test reports how long Klippy waited.

What B, A, C, D really printed is read from Klippy itself: after each object's block the test macro
``LW_MARK`` stores the toolhead's commanded position, which stays where the previous object ended
when Klippy drops an excluded object's moves; the test extruder
(``klippy_extras/layerwatch_test_extruder.py``: Klippy has no MCU here, so no real extruder) adds
up the filament Klippy pushed, which must be exactly A, C, D on every layer and B up to its cancel.
"""

import dataclasses
import re
import threading

import httpx
import numpy as np
import pytest
from moonraker_stack import MoonrakerStack, require_installed, running, until

from layerwatch.analysis.failure_kinds import FAILURE_KINDS
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode.objects import read_objects, without_objects
from layerwatch.gcode.reader import read_toolpath
from layerwatch.geometry.pose import locate_bed
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter
from layerwatch.monitor.service import Monitor
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera
from layerwatch.simulate.plate import plate_gcode

pytestmark = [pytest.mark.moonraker, pytest.mark.slow, pytest.mark.xdist_group("servers")]

#: layers of the plate printed; B comes off the bed from ONSET; a layer's least printing time, s
N_LAYERS, ONSET, LAYER_S = 12, 4, 1.0
#: the detached part's move, mm: away from A (-x) and D (+y); the simulation's seed
MOVE_MM, SEED = (1.8, -1.8), 1
#: the last layers of B Klippy may print (two layers in a row decide: after ONSET + 1 or ONSET + 2)
CUTS = (ONSET + 1, ONSET + 2)
#: the wait for the monitor's verdict on the layer before: steps of STEP_S, at most WAIT_STEPS of them
STEP_S, WAIT_STEPS = 0.2, 300
OBJECTS = "ABCD"

EXTRA_CFG = """[exclude_object]

[layerwatch_test_extruder]

[gcode_macro LW_MARK]
variable_seen: ''
gcode:
  {% set pos = printer.toolhead.position %}
  {% set mark = params.OBJ ~ params.LAYER ~ '@' ~ (pos.x|round(2)) ~ '/' ~ (pos.y|round(2)) ~ ' ' %}
  SET_GCODE_VARIABLE MACRO=LW_MARK VARIABLE=seen VALUE="'{seen ~ mark}'"

[gcode_macro LW_JUDGED]
variable_layer: -1
variable_waited: 0
gcode:
  {% if layer < params.LAYER|int %}
    SET_GCODE_VARIABLE MACRO=LW_JUDGED VARIABLE=waited VALUE={waited + 1}
    LAYERWATCH_TEST_LAYER_TIME SECONDS=@STEP_S@
  {% endif %}
""".replace("@STEP_S@", str(STEP_S))


def _wait_judged(layer: int) -> list[str]:
    """Klippy waits (at most ``WAIT_STEPS * STEP_S``) until the monitor has judged ``layer``."""
    return [f"LW_JUDGED LAYER={layer}"] * WAIT_STEPS


def plate_text() -> str:
    """The demo plate's first ``N_LAYERS`` layers: a layer time and the wait for the verdict on the layer
    before, a mark per object block and a trigger per layer."""
    text = plate_gcode(read_toolpath(PART_GCODE)).decode()
    head, *layers = text.split(";LAYER_CHANGE\n")
    out = [head.rstrip("\n")]
    for i, chunk in enumerate(layers[:N_LAYERS]):
        for ln in chunk.rstrip("\n").split("\n"):  # (the end G-code is in the last layer's chunk: not taken)
            out.append(ln)
            if ln.startswith("G1 Z"):
                out.append(f"LAYERWATCH_TEST_LAYER_TIME SECONDS={LAYER_S}")  # the layer's printing time
                if i:
                    out += _wait_judged(i - 1)  # ... at least as long as the analysis of the layer before
            m = re.match(r"EXCLUDE_OBJECT_END NAME=part_([A-D])", ln)
            if m:
                out.append(f"LW_MARK OBJ={m.group(1)} LAYER={i}")
        z = re.search(r";Z:([\d.]+)", chunk).group(1)
        out.append(f"LAYERWATCH_SNAPSHOT LAYER={i} Z={z}")
    out.append(f"LAYERWATCH_TEST_LAYER_TIME SECONDS={LAYER_S}")  # the end G-code: the last photo is taken
    out += _wait_judged(N_LAYERS - 1)
    return "\n".join(out) + "\n"


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


def _inside(box, xy):
    return box[0] - 0.01 <= xy[0] <= box[2] + 0.01 and box[1] - 0.01 <= xy[1] <= box[3] + 0.01


class _PlateCamera:
    """Photos of the plate as Klippy printed it, simulated in advance: B detached from ``ONSET`` and, once
    Klippy reports it excluded, left out of the layers after the last one Klippy printed (its ``LW_MARK``
    inside B's box); ``cut`` is that layer (a cut not in ``CUTS`` is simulated when asked, and counted)."""

    def __init__(self, stack, tp, objects, truth, tv, failures):
        self.stack, self.tp, self.objects, self.b = stack, tp, objects, objects.objects[1]
        self.args = (truth, tv, failures)
        sim = self._sim(None)
        self.bed = sim.bed_photo()
        self.photos = {None: [sim.frame(i).photo for i in range(tp.n_layers)]}
        for cut in CUTS:
            self._simulate(cut)
        self.cut: int | None = None
        self.late: list[int] = []  # cuts simulated while printing

    def _sim(self, cut: int | None) -> PrintSimulator:
        sim = PrintSimulator(self.tp, *self.args, seed=SEED)
        if cut is not None:
            sim.tp = without_objects(self.tp, self.objects, {self.b.index: cut})
        return sim

    def _simulate(self, cut: int) -> None:
        sim = self._sim(cut)
        self.photos[cut] = self.photos[None][:cut + 1] + [sim.frame(i).photo for i in range(cut + 1, self.tp.n_layers)]

    def __call__(self, layer: int) -> np.ndarray:
        if layer < 0:  # the empty-bed check at job start
            return self.bed
        if self.cut is None and "PART_B" in self.stack.query("exclude_object")["exclude_object"]["excluded_objects"]:
            printed = [i for i, xy in _marks(self.stack)["B"].items() if _inside(self.b.bbox_mm, xy)]
            self.cut = max(printed, default=-1)
            if self.cut not in self.photos:
                self.late.append(self.cut)
                self._simulate(self.cut)
        return self.photos[self.cut][layer]


class _Monitor(Monitor):
    """The monitor, telling the test's Klippy (``LW_JUDGED``) each layer it has judged and acted on."""

    def __init__(self, url, *args, **kw):
        super().__init__(*args, **kw)
        self.url = url

    def finish_layer(self, trigger, res, top=None):
        res = super().finish_layer(trigger, res, top)
        if res.layer >= 0:
            httpx.post(self.url + "/printer/gcode/script", timeout=60,
                       params={"script": f"SET_GCODE_VARIABLE MACRO=LW_JUDGED VARIABLE=layer VALUE={res.layer}"})
        return res


def test_failure_on_one_object_cancels_exactly_that_object_on_a_real_klippy(stack):
    text = plate_text()
    tp = read_toolpath(text.encode())
    objects = read_objects(text.encode(), tp)
    names = [o.klipper_name for o in objects.objects]
    assert objects.style == "exclude_object" and names == [f"PART_{n}" for n in OBJECTS] and tp.n_layers == N_LAYERS
    boxes = {n: o.bbox_mm for n, o in zip(OBJECTS, objects.objects, strict=True)}
    # the job: the demo part's configuration, every kind's action cancel_object (as `layerwatch demo --plate`)
    kinds = {k: {"action": "cancel_object"} for k in FAILURE_KINDS}
    cfg = resolve_config(PART_CONFIG, flags={"policy": {"kinds": kinds}}).config
    tv = cfg.topview.topview()
    truth = default_camera(tv, image_size=(1280, 720))
    x0, y0, x1, y1 = boxes["B"]
    fail = Failure("detachment", ONSET, float(np.hypot(*MOVE_MM)), SEED, offset_mm=MOVE_MM,
                   within_mm=(x0 - 0.5, y0 - 0.5, x1 + 0.5, y1 + 0.5))
    photos = _PlateCamera(stack, tp, objects, truth, tv, [fail])  # before the print: the camera answers at once
    camera = locate_bed(dataclasses.replace(truth, rvec=None, tvec=None), photos.photos[None][0], cfg.markers, tv)
    pipe = LayerPipeline(tp, camera, cfg, bed_photo=photos.bed)
    printer = MoonrakerPrinter(stack.url)
    mon = _Monitor(stack.url, printer, SimCamera(photos), pipe, PausePolicy(cfg.policy), objects=objects)
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("report", mon.run(poll_s=0.05)), daemon=True)
    try:
        assert printer.wait_connected(15)
        stack.upload_and_print("lw_plate.gcode", text)
        t.start()
        until(lambda: stack.query("print_stats")["print_stats"]["state"] == "complete",
              30 + (LAYER_S + WAIT_STEPS * STEP_S) * (N_LAYERS + 1), "the plate to finish")
        t.join(30)
        assert not t.is_alive() and out["report"].outcome == "done"
        excluded = stack.query("exclude_object")["exclude_object"]
        assert excluded["excluded_objects"] == ["PART_B"]  # exactly that object, as Klippy reports it
        stops = [d for d in mon.report.decisions if d.stops]
        assert [d.action for d in stops] == ["cancel_object"], [(d.action, d.reason) for d in stops]
        decided = stops[0].layer
        # decided by detection: two layers in a row (consecutive_layers=2) after the onset, not before
        assert ONSET + 1 <= decided <= ONSET + 2, (decided, stops[0].reason)
        results = {r.layer: r for r in mon.report.results}
        assert all(results[i].regions for i in (decided - 1, decided))  # the detector's regions, ...
        assert objects.locate(tp, stops[0].regions, decided).single == 1  # ... which lie on B alone
        assert not [r for r in mon.report.results if r.layer < ONSET and r.decision != "none"]  # nothing before
        # later layers: B's remains are still in the photos, and raise no alarm
        later = [r for r in mon.report.results if r.layer > decided]
        assert len(later) == N_LAYERS - 1 - decided and all(r.decision == "none" for r in later), (
            [(r.layer, r.decision, r.decision_reason, [tuple(round(v, 1) for v in o.bbox_mm) for o in r.outside_regions])
             for r in later], photos.cut, _marks(stack)["B"], [r.layer for r in mon.report.results])
        marks = _marks(stack)
        for name in "ACD":  # the others print every layer
            assert sorted(marks[name]) == list(range(N_LAYERS)) and all(_inside(boxes[name], xy)
                                                                      for xy in marks[name].values())
        skipped = [i for i, xy in marks["B"].items() if not _inside(boxes["B"], xy)]
        assert all(_inside(boxes["B"], marks["B"][i]) for i in range(decided + 1))  # B printed up to the decision
        assert skipped == list(range(skipped[0], N_LAYERS)) and skipped[0] <= decided + 1, marks["B"]
        assert photos.cut == skipped[0] - 1 and photos.cut in CUTS and not photos.late  # photos followed Klippy
        # the filament Klippy pushed: every layer of A, C, D and B's layers before the cancel, nothing more
        per_object_layer = np.zeros((len(OBJECTS), N_LAYERS))
        for lay in tp.layers:
            obj = objects.segment_object[lay.seg_start:lay.seg_stop]
            for k in range(len(OBJECTS)):
                per_object_layer[k, lay.index] = tp.e[lay.seg_start:lay.seg_stop][obj == k].sum()
        expected = per_object_layer[[0, 2, 3]].sum() + per_object_layer[1, :skipped[0]].sum()
        extruded = stack.query("layerwatch_test_extruder")["layerwatch_test_extruder"]["extruded"]
        assert extruded == pytest.approx(expected, abs=1e-2)
        waited = stack.query("gcode_macro LW_JUDGED")["gcode_macro LW_JUDGED"]["waited"]
        print(f"\nKlippy: cancel decided after layer {decided} ({stops[0].reason}), B skipped from layer "
              f"{skipped[0]}, {extruded:.1f} mm filament pushed; Klippy waited {waited * STEP_S:.1f} s in all "
              f"for the verdicts ({N_LAYERS} layers of {LAYER_S:g} s)")
        # from the next layer the reference leaves B out
        new = pipe.toolpath
        later_lines = new.line[new.layers[decided + 1].seg_start:]
        assert not np.isin(later_lines, tp.line[objects.segment_object == 1]).any()
        # the cause where the user looks: the printer's display and the console, through Moonraker's API
        msg = stack.query("display_status")["display_status"]["message"]
        assert msg.startswith(f"layerwatch: cancel object L{decided} ") and msg.endswith(" part_B"), msg
        store = httpx.get(stack.url + "/server/gcode_store", params={"count": 200}, timeout=5).json()
        assert any("layerwatch: cancel object" in m["message"] for m in store["result"]["gcode_store"])
    finally:
        mon.stop_event.set()
        if t.is_alive():
            t.join(10)
        printer.close()
