"""Does the camera-fault gate stop false pauses without hiding real failures? (issue 19)

Run: ``python benchmarks/frame_quality_gate.py`` (about ten minutes on one core). Every
monitor runs with the default ``[frame_quality]`` settings (``excuse_late_frames`` on).

1. **Camera faults on clean prints.** The bundled example part is printed on the
   virtual printer and watched by the real :class:`Monitor` (``LayerPipeline`` +
   ``PausePolicy`` with the recommended settings, wait for each verdict); the
   simulated 720p camera delivers clean frames except on layers 8-13, where one
   kind of camera fault is injected (black, over-exposed, pure noise, JPEG
   quality 5, the previous layer's frame again with fresh noise, a frozen noisy
   stream, a defocused frame, every frame one layer late from layer 8 on, a camera
   bumped 30 px). The late stream comes three times: as copies of the previous
   layer's frame with fresh noise (``lagging_stream``: its first late frame is a
   repeat the gate refuses), as new exposures of the previous layer
   (``lagging_stream_fresh``: the light and sensor of the trigger's own moment, so
   its first late frame is no repeat and must be told over the series), and as new
   exposures from layer 10 to the end (``late_from_10_fresh``: the part widens at
   layer 10, so that first late frame, a picture of layer 9 without progress, is far
   from layer 10's reference). Three whole-print faults follow:
   ``lagged_whole_print`` and ``lagged_whole_print_fresh`` (from the first layer on,
   every frame is a photo of the layer before: the empty bed at layer 0) and
   ``bumped_whole_print`` (the camera shifted by 30 px from layer 1 on). Pauses are
   counted with the gate on, off (the baseline), and on with ``excuse_late_frames`` off
   (the old default). Target: 0 pauses with the gate on.
2. **Real failures still pause through the monitor.** The same print with a real
   failure and the gate on: nothing extruded from layer 8 (a stall: frames stop
   changing, each a new exposure), spaghetti from layer 8, and both behind a camera
   one layer late from layer 4 (new exposures). Target: each pauses, within two layers
   of the failure's onset (for the late camera, of the onset's first late picture).
3. **Real failures pass the gate.** Every frame of the evaluation's failure
   scenarios (``evaluate.harness.plan_frames``, every failure type of the
   simulator) in which the failure is visible is checked as the monitor checks it:
   by the gate against the frame of the layer before, with the bed markers found in
   it; then by the late-camera check over the scenario's frames
   (:meth:`~layerwatch.monitor.camera_checks.LateStream.check`: explained by the
   previous layer's reference, progress since the previous frame, a slip before). A
   frame passes when the gate does not refuse it and the late-camera check does not
   excuse it as one layer late (an excused frame is still judged against the layer
   before, where the failure may still pause; counting it missed is the stricter
   measure). Two figures: with the camera on time so far (what the monitor does on a
   print whose camera never slipped) and, the worst case, as if the stream had
   slipped just before each scenario. Target: >= 0.97.
4. **Real photos.** The photos in ``/work/shared/data/photos`` (real cameras:
   exposure drift, glare, glass beds, dark filament) pass the gate (no previous frame).
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from layerwatch.analysis.frame_quality import FrameQualitySettings, assess_frame
from layerwatch.evaluate.harness import plan_frames
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.geometry.pose import locate_bed
from layerwatch.monitor.camera_checks import LateStream, MarkerWatch
from layerwatch.monitor.cameras import SimCamera
from layerwatch.monitor.frame_checks import FrameChecks
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.monitor.service import CAMERA_FAULT, Monitor
from layerwatch.pipeline.config import recommended_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.step import LayerPipeline
from layerwatch.simulate import Failure, PrintSimulator, default_camera

PHOTOS = Path("/work/shared/data/photos")
N_LAYERS = 20
#: about this many frames are planned for the failure measurement (about half show a failure)
FAILURE_FRAMES = 240
FAULT_LAYERS = range(8, 14)


def _noisy(img: np.ndarray, rng: np.random.Generator, sigma: float = 3.0) -> np.ndarray:
    return np.clip(img + rng.normal(0, sigma, img.shape), 0, 255).astype(np.uint8)


def _jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    return cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])[1], cv2.IMREAD_COLOR)


def camera_faults(frames: list[np.ndarray], seed: int = 0) -> dict:
    """Kind -> ``frame(layer)`` returning the clean frame, or on :data:`FAULT_LAYERS` the faulty one."""
    rng = np.random.default_rng(seed)
    first = FAULT_LAYERS[0]
    kinds = {
        "black": lambda i: _noisy((frames[i] * 0.03).astype(np.uint8), rng, 1.5),
        "over_exposed": lambda i: np.clip(frames[i].astype(np.float32) * 4 + 60, 0, 255).astype(np.uint8),
        "pure_noise": lambda i: rng.integers(0, 256, frames[i].shape, dtype=np.uint8),
        "jpeg_q5": lambda i: _jpeg(frames[i], 5),
        # the previous layer's frame delivered again, on every other fault layer (a camera buffer lag)
        "lagged": lambda i: _jpeg(_noisy(frames[i - 1], rng), 90) if (i - first) % 2 == 0 else frames[i],
        "frozen_noisy": lambda i: _jpeg(_noisy(frames[first - 1], rng), 85),
        "defocused": lambda i: cv2.GaussianBlur(frames[i], (0, 0), 6),
        # every frame one layer late from the first fault layer on: only its first frame repeats one already
        # seen; the later ones are new pictures of the wrong layer (the lag check sees them)
        "lagging_stream": lambda i: _jpeg(_noisy(frames[i - 1], rng), 90),
        "bumped": lambda i: _shifted(frames[i]),
    }
    return {k: (lambda i, f=f: f(i) if i in FAULT_LAYERS else frames[i]) for k, f in kinds.items()}


def _shifted(img: np.ndarray, dx: float = 24.0, dy: float = -18.0) -> np.ndarray:
    """The frame of a camera bumped by (dx, dy) px (30 px here)."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REPLICATE)


def whole_print_faults(frames: list[np.ndarray], bed: np.ndarray, seed: int = 1) -> dict:
    """Kind -> ``frame(layer)`` for a camera fault that lasts the whole print."""
    rng = np.random.default_rng(seed)
    return {
        # a stream one layer late from the start: layer 0 gets the empty bed, layer k the photo of layer k-1
        "lagged_whole_print": lambda i: _jpeg(_noisy(frames[i - 1] if i else bed, rng), 90),
        "bumped_whole_print": lambda i: _shifted(frames[i]) if i else frames[0],
    }


def exposed(sim: PrintSimulator, shown: int, taken: int) -> np.ndarray:
    """A new photo of the print after layer ``shown`` (the empty bed when < 0) taken at trigger ``taken``.

    The simulator's photographic state (light position and intensity, exposure and white-balance
    drift, blur, sensor noise) is drawn per trigger index; here it is that of ``taken``, so a
    camera one layer late delivers a fresh exposure of the previous layer, not a copy of its frame.
    Call in increasing ``shown`` (the simulator only prints forward).
    """
    shoot = sim.cam.shoot
    sim.cam.shoot = lambda h, mat, index, *rest: shoot(h, mat, taken, *rest)
    try:
        return sim.bed_photo() if shown < 0 else sim.frame(shown).photo
    finally:
        sim.cam.shoot = shoot


def late_frames(tp, truth, tv, late: range, failures=(), seed: int = 3) -> list[np.ndarray]:
    """Frames of a print (``failures`` injected) whose camera is one layer late on the triggers in ``late``."""
    sim = PrintSimulator(tp, truth, tv, list(failures), seed=seed)
    return [exposed(sim, i - 1, i) if i in late else sim.frame(i).photo for i in range(N_LAYERS)]


def fresh_faults(tp, truth, tv) -> dict:
    """Kind -> ``frame(layer)`` for a late camera whose pictures are new exposures (no repeats)."""
    stretch = late_frames(tp, truth, tv, FAULT_LAYERS)
    # from layer 10 on (where the part widens again: the first late frame is far from layer 10's reference)
    behind = late_frames(tp, truth, tv, range(10, N_LAYERS))
    whole = late_frames(tp, truth, tv, range(N_LAYERS))
    return {"lagging_stream_fresh": stretch.__getitem__, "late_from_10_fresh": behind.__getitem__,
            "lagged_whole_print_fresh": whole.__getitem__}


def _job():
    logging.getLogger("layerwatch").setLevel(logging.ERROR)
    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    data = PART_GCODE.read_bytes()
    tp = read_toolpath(data)
    truth = default_camera(tv)
    sim = PrintSimulator(tp, truth, tv, [], seed=3)
    frames = [sim.frame(i).photo for i in range(N_LAYERS)]
    cam = locate_bed(dataclasses.replace(truth, rvec=None, tvec=None), frames[0], cfg.markers, tv)
    prepared = insert_snapshots(data, cfg.snapshot.model_copy(update={"profile": "octoprint"}), cfg.printer)
    cut = prepared.find(f"layerwatch snapshot layer={N_LAYERS} ".encode())
    return cfg, tp, truth, LayerPipeline(tp, cam, cfg), prepared[: prepared.rfind(b"\n", 0, cut)], frames, \
        sim.bed_photo()


def watch(cfg, pipe, gcode, frame, bed: np.ndarray, gate: bool = True, **quality):
    """The real monitor over one simulated print (``frame(layer)``; the bed at job start), default gate
    (``quality``: settings that differ from the defaults)."""
    pipe.new_print()
    mon = Monitor(VirtualPrinter(gcode), SimCamera(lambda i: bed if i < 0 else frame(i)), pipe, PausePolicy(cfg.policy),
                  wait_for_verdict=True, frame_quality=FrameQualitySettings(**quality) if gate else None)
    return mon.run(poll_s=0.001)


def clean_print_pauses(cfg, pipe, gcode, frames, bed, kinds=None, extra=None,
                       excuse_off: bool = True) -> dict[str, dict[str, int]]:
    """Per fault kind: pauses with the gate on and off (and on with ``excuse_late_frames`` off), frames refused,
    frames judged one layer late, alerts.

    ``kinds``: the kinds to run (all of :func:`camera_faults`, :func:`whole_print_faults` and
    ``extra``). ``refused_clean`` counts refused frames outside :data:`FAULT_LAYERS` (for the
    whole-print kinds every layer is faulty, so it is not counted). ``excuse_off``: also run the
    old default (``pauses_excuse_off``; a third of the time, which the test that asserts nothing
    on it skips).
    """
    faults = {**camera_faults(frames), **whole_print_faults(frames, bed), **(extra or {})}
    out = {}
    for kind, frame in faults.items():
        if kinds is not None and kind not in kinds:
            continue
        row = {}
        if excuse_off:
            row["pauses_excuse_off"] = watch(cfg, pipe, gcode, frame, bed, excuse_late_frames=False).pauses
        for gate in (True, False):
            rep = watch(cfg, pipe, gcode, frame, bed, gate)
            row["pauses_gate_on" if gate else "pauses_gate_off"] = rep.pauses
            if gate:
                whole = kind.endswith("whole_print")
                row["refused"] = sum(r.status == CAMERA_FAULT for r in rep.results)
                row["lagged"] = rep.lagged_frames
                row["refused_clean"] = 0 if whole else sum(r.status == CAMERA_FAULT and r.layer not in FAULT_LAYERS
                                                           for r in rep.results)
                row["alerts"] = rep.alerts
        out[kind] = row
    return out


def failure_pauses(cfg, tp, truth, pipe, gcode, bed, **quality) -> dict[str, tuple[int, int | None, int]]:
    """Real failures watched by the monitor (default gate): name -> (pauses, first stopping layer, onset seen).

    ``onset seen``: the trigger whose picture first shows the failure's onset layer (one later
    behind the late camera). ``quality``: gate settings that differ from the defaults.
    """
    tv = cfg.topview.topview()
    stall, spaghetti = Failure("nothing_extruded", onset=8), Failure("spaghetti", onset=8, seed=1)
    late = range(4, N_LAYERS)
    runs = {
        "nothing_extruded_8": (late_frames(tp, truth, tv, range(0), [stall]), 8),
        "spaghetti_8": (late_frames(tp, truth, tv, range(0), [spaghetti]), 8),
        "late_from_4+nothing_extruded_8": (late_frames(tp, truth, tv, late, [stall]), 9),
        "late_from_4+spaghetti_8": (late_frames(tp, truth, tv, late, [spaghetti]), 9),
    }
    out = {}
    for name, (frames, seen) in runs.items():
        rep = watch(cfg, pipe, gcode, frames.__getitem__, bed, **quality)
        stops = [d.layer for d in rep.decisions if d.stops]
        out[name] = (rep.pauses, stops[0] if stops else None, seen)
    return out


def _gate_reasons(photo: np.ndarray, previous: np.ndarray | None, markers: MarkerWatch | None,
                  box: tuple[slice, slice] | None = None) -> list[str]:
    """The gate's reasons as the monitor's :class:`FrameChecks` gives them (``box``: its region of interest)."""
    return assess_frame(photo, previous, box=box, **(markers(photo) if markers is not None else {})).reasons


def failure_frames_passed(tp, truth, cfg, pipe, n_layers: int = 120, seed: int = 0) -> dict:
    """Failure frames the monitor's camera-fault checks let through (the gate, then the late-camera check).

    Each scenario's frames (the layer before the onset, then the failure's) go through the gate
    against the frame before and, when it passes, through the pipeline and
    :meth:`LateStream.check` in order, as the monitor runs them: once with the stream on time so
    far and once as if it had slipped just before the scenario (the worst case).

    Returns
    -------
    dict
        ``total`` (Counter per failure type), ``passed`` and ``passed_slipped`` (Counter),
        ``refused`` and ``refused_slipped`` (list of (scenario, layer, reasons)), ``checked``
        (frames the previous layer's reference was asked about).
    """
    tv = cfg.topview.topview()
    markers = MarkerWatch.of_pipeline(pipe, FrameQualitySettings().max_marker_shift_px)  # as the monitor's
    roi = FrameChecks(pipe, FrameQualitySettings(), 3)  # the monitor's region of interest ([frame_quality] roi)
    out = {"total": Counter(), "passed": Counter(), "passed_slipped": Counter(), "refused": [],
           "refused_slipped": [], "checked": 0}
    for k, (scen, layers) in enumerate(plan_frames(tp, n_layers, seed=seed)):
        if not scen.failures:
            continue
        sim = PrintSimulator(tp, truth, tv, scen, seed=seed * 1000 + k)
        kind = scen.failures[0].type
        pipe.new_print()
        streams = {"": LateStream(3), "_slipped": LateStream(3)}
        streams["_slipped"].slipped = True
        previous = None
        for i in layers:
            frame = sim.frame(i)
            counted = bool(frame.meta.get("failed")) and i > 0
            reasons = _gate_reasons(frame.photo, previous, markers, roi.roi(frame.photo.shape))
            previous = frame.photo
            verdicts = dict.fromkeys(streams, reasons)
            if not reasons:
                res = pipe.process(frame.photo, i)
                for key, late in streams.items():
                    if res.status != "ok":
                        continue
                    check = late.check(pipe, frame.photo, res, cfg.policy)
                    out["checked"] += counted and check.verdict is not None and key == ""
                    verdicts[key] = [check.judged.message] if check.judged is not None else []
            else:
                for late in streams.values():
                    late.interrupted()
            if not counted:
                continue
            out["total"][kind] += 1
            for key in streams:
                out["passed" + key][kind] += not verdicts[key]
                if verdicts[key]:
                    out["refused" + key].append((scen.name, i, verdicts[key]))
    return out


def real_photos() -> list[tuple[str, bool, list[str]]]:
    out = []
    for p in sorted(PHOTOS.glob("*.jp*g")):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is not None:
            q = assess_frame(img)
            out.append((p.name, q.ok, q.reasons))
    return out


def main() -> None:
    cfg, tp, truth, pipe, gcode, frames, bed = _job()
    tv = cfg.topview.topview()
    print(f"1. camera faults on layers {FAULT_LAYERS[0]}-{FAULT_LAYERS[-1]} (or the whole print) of a clean "
          f"{N_LAYERS}-layer print (virtual printer, LayerPipeline, PausePolicy, recommended settings, default gate)")
    rows = clean_print_pauses(cfg, pipe, gcode, frames, bed, extra=fresh_faults(tp, truth, tv))
    for kind, r in rows.items():
        print(f"   {kind:24s} pauses gate on {r['pauses_gate_on']}  gate off {r['pauses_gate_off']}  "
              f"excuse off {r['pauses_excuse_off']}  frames refused {r['refused']} (of which clean {r['refused_clean']}), judged as one layer late "
              f"{r['lagged']}, alerts {r['alerts']}")
    print(f"   total pauses: gate on {sum(r['pauses_gate_on'] for r in rows.values())}, "
          f"gate off {sum(r['pauses_gate_off'] for r in rows.values())}")
    print("2. real failures watched by the monitor (default gate; baseline: excuse_late_frames off, the old "
          "default): pauses, first stopping layer")
    off = failure_pauses(cfg, tp, truth, pipe, gcode, bed, excuse_late_frames=False)
    for name, (pauses, stop, seen) in failure_pauses(cfg, tp, truth, pipe, gcode, bed).items():
        late = "-" if stop is None else f"{stop - seen:+d}"
        print(f"   {name:32s} pauses {pauses}  first stop at layer {stop} (first picture of the onset: "
              f"layer {seen}; {late} layers); excuse off: pauses {off[name][0]}, first stop at layer {off[name][1]}")
    res = failure_frames_passed(tp, truth, cfg, pipe, n_layers=FAILURE_FRAMES)
    total = sum(res["total"].values())
    print("3. failure frames the monitor's camera-fault checks let through (the gate, then the late-camera check "
          f"over each scenario's frames; the previous layer's reference was asked about {res['checked']} of them)")
    for kind in sorted(res["total"]):
        print(f"   {kind:14s} camera on time {res['passed'][kind]}/{res['total'][kind]}  "
              f"slipped just before {res['passed_slipped'][kind]}/{res['total'][kind]}")
    for key, label in (("", "camera on time"), ("_slipped", "slipped just before")):
        n = sum(res["passed" + key].values())
        print(f"   all, {label}: {n}/{total} = {n / total:.3f}")
        for name, i, reasons in res["refused" + key]:
            print(f"   refused ({label}): {name} layer {i}: {'; '.join(reasons)}")
    photos = real_photos()
    print(f"4. real photos passing: {sum(ok for _, ok, _ in photos)}/{len(photos)}")
    for name, ok, reasons in photos:
        if not ok:
            print(f"   refused: {name}: {'; '.join(reasons)}")


if __name__ == "__main__":
    main()
