"""The scene channel on simulated series: a failure beside the part stays counted, clean prints stay quiet.

Every test here simulates a print (photo per layer), so they are slow.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from layerwatch.analysis.scene_change import to_working
from layerwatch.cli import main
from layerwatch.evaluate.results import ResultsFolder
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.farm.simcam import SimPrint
from layerwatch.gcode import read_toolpath
from layerwatch.geometry.camera import CameraModel
from layerwatch.pipeline.config import load_config, recommended_config, resolve_config
from layerwatch.pipeline.policy import PausePolicy
from layerwatch.pipeline.scene import SceneModel, load_bed_photo
from layerwatch.pipeline.step import LayerPipeline, judge_layers
from layerwatch.simulate import Failure, PrintSimulator, SimSettings, default_camera

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def spaghetti(tmp_path_factory):
    """`layerwatch simulate -f spaghetti@12 -n 20`, analysed with and without the paper's settings."""
    root = tmp_path_factory.mktemp("spaghetti")
    sim = root / "sim"
    assert main(["simulate", "-f", "spaghetti@12", "-n", "20", "-o", str(sim)]) == 0
    photos = sorted(str(p) for p in sim.glob("layer_*.png") if not p.stem.endswith(("_truth", "_area")))
    off = root / "scene_off.toml"
    off.write_text(PART_CONFIG.read_text() + "\n[scene]\nenabled = false\n")
    runs = {}
    for name, extra in (("default", []), ("paper", ["--paper-settings"]), ("off", ["-c", str(off)])):
        out = root / name
        rc = main(["analyze", "--gcode", str(PART_GCODE), "--camera", str(sim / "camera.toml"), "-o", str(out),
                   *extra, *photos])
        assert rc == 0
        tv = load_config(PART_CONFIG).topview.topview()
        runs[name] = (ResultsFolder(out, tv).done(), json.loads((out / "summary.json").read_text()))
    return sim, runs


def test_spaghetti_beside_the_layer_stays_counted_and_pauses(spaghetti):
    sim, runs = spaghetti
    assert CameraModel.load(sim / "camera.toml").bed_photo == str((sim / "bed.png").resolve())
    results, summary = runs["default"]
    later = [results[i] for i in range(13, 20)]
    assert all(r.status == "ok" for r in later)
    seen = [r.outside_anomalous_mm2 for r in later]
    assert sum(a > 0 for a in seen) >= 6, seen  # today: a% 0.0 on every later layer
    assert all(r.scene is not None and r.scene.baseline == "bed photo" for r in later)
    assert 12 <= summary["paused_at_layer"] <= 17 and "beside the print" in summary["pause_reason"], summary
    assert all(r.outside_anomalous_mm2 == 0 for r in (results[i] for i in range(0, 12))), "clean layers changed"


def test_paper_settings_keep_the_paper_single_photo_method(spaghetti):
    _, runs = spaghetti
    results, summary = runs["paper"]
    assert all(r.scene is None and r.outside_anomalous_mm2 == 0 for r in results.values())
    assert "beside the print" not in str(summary["pause_reason"])


def test_without_the_scene_channel_the_clump_is_lost_and_a_percent_is_unchanged(spaghetti):
    _, runs = spaghetti
    off, summary = runs["off"]
    on, _ = runs["default"]
    # the report: 0.0 after layer 12. The clump is lost: nothing beside the part, and a% stays at the
    # clean level (the changed-as-predicted channel marks a clean ring wall on layer 14: 0.4 %, its false-region
    # rate on clean layers, docs/evaluation/layer_change.md)
    assert all(not off[i].outside_regions and off[i].outside_anomalous_mm2 == 0 for i in range(13, 20))
    assert all(off[i].anomaly_ratio < 0.01 for i in range(13, 20))
    assert summary["paused_at_layer"] is None
    assert all(on[i].anomaly_ratio == off[i].anomaly_ratio for i in range(20))  # a% stays eq. 5


def _series(frames, settings=None, bed=True, seed=5, n=16):
    """Judge a clean simulated print (recommended settings); ``frames(i, photo)`` may edit or drop photos."""
    tp = read_toolpath(PART_GCODE)
    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    cam = default_camera(tv)
    sim = PrintSimulator(tp, cam, tv, (), seed=seed, settings=settings)
    pipe = LayerPipeline(tp, cam, cfg, bed_photo=sim.bed_photo() if bed else None)
    photos = ((i, frames(i, sim.frame(i).photo)) for i in range(n))
    return pipe, list(judge_layers(pipe, PausePolicy(cfg.policy), ((i, p) for i, p in photos if p is not None)))


def test_a_clean_print_with_exposure_and_white_balance_drift_never_pauses():
    drift = SimSettings(exposure_drift=0.25, colour_drift=0.12, light_intensity_jitter=0.15)
    _, judged = _series(lambda i, p: p, settings=drift, n=20)
    assert all(res.status == "ok" for res, _ in judged)
    assert not any(d.stops for _, d in judged)
    assert not any("beside the print" in d.reason for _, d in judged)
    assert max(res.outside_anomalous_mm2 for res, _ in judged) < 12.0


def test_a_black_and_a_skipped_photo_do_not_poison_the_scene_nor_pause():
    kept = {}

    def frames(i, photo):
        if i == 6:
            kept["before"] = None
            return np.zeros_like(photo)  # the lamp was off
        if i == 9:
            return None  # no photo for layer 9
        return photo

    pipe, judged = _series(frames)
    by_layer = {res.layer: (res, d) for res, d in judged}
    black, decision = by_layer[6]
    assert black.status == "error" and black.message.startswith("frame rejected")
    assert decision.action == "notify"
    assert not any(d.stops for _, d in judged)
    after_gap = by_layer[10][0]
    assert after_gap.status == "ok" and after_gap.outside_anomalous_mm2 == 0
    assert pipe.scene.baseline == "bed photo" and pipe.scene.last_layer == 15


def test_the_black_frame_leaves_the_expected_appearance_as_it_was():
    tp = read_toolpath(PART_GCODE)
    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    cam = default_camera(tv)
    sim = PrintSimulator(tp, cam, tv, (), seed=2)
    pipe = LayerPipeline(tp, cam, cfg, bed_photo=sim.bed_photo())
    assert pipe.process(sim.frame(0).photo, 0).status == "ok"
    before = pipe.scene.expected.copy()
    res = pipe.process(np.zeros((720, 1280, 3), np.uint8), 1)
    assert res.status == "error" and "frame rejected" in res.message
    assert np.array_equal(pipe.scene.expected, before)


def test_bed_photo_of_another_pose_is_dropped_with_a_note(tmp_path):
    tp = read_toolpath(PART_GCODE)
    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    cam = default_camera(tv)
    sim = PrintSimulator(tp, cam, tv, (), seed=3)
    moved = np.roll(sim.bed_photo(), (40, 90), axis=(0, 1))
    path = tmp_path / "bed.png"
    cv2.imwrite(str(path), moved)
    photo, note = load_bed_photo(path, cam, given=True)
    assert photo is None and "another camera position" in note
    # without the marker check (e.g. ArUco markers), the first frame's shift against it drops it
    pipe = LayerPipeline(tp, cam, cfg, bed_photo=np.roll(sim.bed_photo(), (10, 20), axis=(0, 1)))
    first = pipe.process(sim.frame(0).photo, 0)
    assert first.status == "ok" and "bed photo does not match" in first.message
    assert pipe.scene.baseline == "first photo"
    later = [pipe.process(sim.frame(i).photo, i) for i in range(1, 4)]
    assert all(r.status == "ok" and r.outside_anomalous_mm2 == 0 for r in later)


def test_bad_bed_photos_at_the_command_line(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert main(["simulate", "--layers", "2", "-o", str(sim)]) == 0
    args = ["analyze", "--gcode", str(PART_GCODE), "--camera", str(sim / "camera.toml"), "-o", str(tmp_path / "r"),
            str(sim / "layer_0000.png"), str(sim / "layer_0001.png")]
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((360, 640, 3), np.uint8))
    capsys.readouterr()
    assert main([*args, "--bed-photo", str(small)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "640x360" in err[0] and "1280x720" in err[0]
    assert main([*args, "--bed-photo", str(tmp_path / "nope.png")]) == 2
    assert "not found" in capsys.readouterr().err
    (sim / "bed.png").unlink()  # recorded with the camera but gone: a note, and the analysis runs
    assert main(args) == 0
    assert "bed photo recorded with the camera" in capsys.readouterr().out.replace("\n", " ")


@pytest.mark.slow
def test_plane_maps_and_body_kept_where_the_print_can_be_seen_give_the_same_records():
    """The scene model keeps its plane maps and printed body on the pixels whose rays can meet the
    print (``reach_box``): the records equal those of a model that keeps them on the whole observed box."""
    tp, cfg = read_toolpath(PART_GCODE), resolve_config(PART_CONFIG).config
    sim = SimPrint(tp, cfg, "spaghetti", 6, 1, keep=16)
    near = LayerPipeline(tp, sim.located, cfg, memo=2)
    whole = LayerPipeline(tp, sim.located, cfg, memo=2)
    whole.scene = SceneModel(sim.located, whole.topview, whole.config.scene)  # no reach: the whole box
    held = [sum(m.nbytes for m in (*p.scene.maps, p.scene.body, p.scene.ledges)) for p in (near, whole)]
    assert held[0] < 0.6 * held[1]
    beside = 0.0
    for i in range(14):
        photo = sim.frame(i)
        a, b = (p.process(photo, i).to_dict() for p in (near, whole))
        for d in (a, b):
            d.pop("timings_ms")
            d["scene"].pop("ms")
        assert a == b, i
        beside += a["outside_anomalous_mm2"]
        assert near.scene.body.shape == near.scene.maps[0].shape[1:]
    assert beside > 0  # the scene channel found the strands beside the print


def test_the_compared_working_image_is_the_whole_one_on_the_observed_box_and_zero_elsewhere():
    """The scene model resizes and blurs only its observed box (nothing else is fitted or scored)."""
    tp, cfg = read_toolpath(PART_GCODE), resolve_config(PART_CONFIG).config
    sim = SimPrint(tp, cfg, "spaghetti", 6, 1, keep=4)
    model = LayerPipeline(tp, sim.located, cfg, memo=2).scene
    assert model is not None
    photo = sim.frame(3)
    whole = to_working(photo, model.size)
    got = model._working(photo)
    inside = np.zeros(model.observed.shape, bool)
    inside[model.box] = True
    assert model.observed[~inside].sum() == 0 and inside.mean() < 0.6
    assert np.array_equal(got[inside], whole[inside])
    assert not got[~inside].any()


@pytest.mark.parametrize("dx, dy", [(1.0, 2.0), (-2.0, 1.0)])
def test_a_camera_nudged_by_two_pixels_since_the_bed_photo_sees_no_change_beside_the_print(dx, dy):
    """The mount flexed a little between the bed photo and the print: the bed photo is moved onto the
    first frame's view, so the bed's dots and edges do not read as material beside the part."""
    move = np.float32([[1, 0, dx], [0, 1, dy]])
    pipe, judged = _series(lambda i, p: cv2.warpAffine(p, move, p.shape[1::-1], borderMode=cv2.BORDER_REPLICATE), n=6)
    assert all(res.status == "ok" for res, _ in judged)
    assert max(res.outside_anomalous_mm2 for res, _ in judged) == 0
    assert not any(d.stops for _, d in judged)
    assert "bed photo moved onto this camera view" in judged[0][0].message and pipe.scene.baseline == "bed photo"


def test_an_object_on_a_lower_floor_beside_the_layer_is_seen_by_the_series_channel():
    """A hex key dropped on the plate behind the ring and the box (the part's lower floor, layer 14's top,
    beside layer 20's footprint): the series channel reports it from its onset on, the clean twin nothing.
    The plate is bright orange, its red channel clipped under the lamp: judged on the channels left."""
    tp = read_toolpath(PART_GCODE)
    cfg = recommended_config(PART_CONFIG)
    tv = cfg.topview.topview()
    cam = default_camera(tv)
    key = Failure("foreign_body", onset=20, size_mm=8.0, center_mm=(110.0, 108.0), seed=7)
    seen = {}
    for name, failures in (("clean", ()), ("key", (key,))):
        sim = PrintSimulator(tp, cam, tv, failures, seed=3)
        pipe = LayerPipeline(tp, cam, cfg, bed_photo=sim.bed_photo())
        seen[name] = []
        for i in range(17, 23):
            frame = sim.frame(i)
            res = pipe.process(frame.photo, i)
            assert res.status == "ok"
            if frame.truth_area is not None:  # the key lies beside the layer, on the floor below it
                fp = pipe.reference(i).footprint
                assert np.count_nonzero(frame.truth_area & fp) < 0.05 * np.count_nonzero(frame.truth_area)
            seen[name].append((res.outside_anomalous_mm2, [r.kind for r in res.outside_regions]))
    assert all(area == 0 for area, _ in seen["clean"]), seen["clean"]
    assert all(area == 0 for area, _ in seen["key"][:3]), seen["key"]
    assert all(area >= 12.0 and "foreign_body" in kinds for area, kinds in seen["key"][3:]), seen["key"]


def test_copy_where_is_numpy_s_masked_copy_into_a_view_of_the_image():
    """The update's masked copy into E and its clipped channels (pipeline/scene._copy_where), float and bool."""
    from layerwatch.pipeline.scene import _copy_where

    rng = np.random.default_rng(4)
    box = (slice(5, 37), slice(9, 60))
    where = rng.random((32, 51)) < 0.4
    for image, values in ((rng.random((50, 70, 3)).astype(np.float32), rng.random((32, 51, 3)).astype(np.float32)),
                          (rng.random((50, 70, 3)) < 0.5, rng.random((32, 51, 3)) < 0.5)):
        want = image.copy()
        np.copyto(want[box], values, where=where[..., None])
        got = image.copy()
        _copy_where(got[box], values, where)
        assert got.dtype == want.dtype and np.array_equal(got, want)
        _copy_where(got[0:0, 0:0], values[0:0, 0:0], where[0:0, 0:0])  # an empty box: nothing to do
        assert np.array_equal(got, want)


def _shaded(cam, corners_mm: np.ndarray, photo: np.ndarray, gain: float, blur_px: float) -> np.ndarray:
    """``photo`` darkened by ``gain`` inside the bed polygon ``corners_mm`` ((k, 3) bed mm), soft-edged."""
    uv = cv2.projectPoints(corners_mm, cam.rvec, cam.tvec, cam.K, cam.dist)[0].reshape(-1, 2)
    mask = np.zeros(photo.shape[:2], np.float32)
    cv2.fillPoly(mask, [np.round(uv).astype(np.int32)], 1.0)
    mask = cv2.GaussianBlur(mask, (0, 0), blur_px)
    return np.clip(photo * (1.0 - (1.0 - gain) * mask[..., None]), 0, 255).astype(np.uint8)


def _cast_shadow(cam, length_mm: float, photo: np.ndarray, gain: float = 0.6) -> np.ndarray:
    """``photo`` with the plate's cast shadow on the bed right of it, ``length_mm`` long, soft-edged (a lamp
    low on the left), darkening the bed by ``gain``."""
    z_mm = length_mm / 2.0
    x0, x1, y0, y1 = 130.0, 130.0 + length_mm, 80.0, 120.0  # the plate spans x 90-130, y 80-120
    corners = np.array([[x0, y0, 0.0], [x1, y0 + 0.3 * z_mm, 0.0], [x1, y1 + 0.3 * z_mm, 0.0], [x0, y1, 0.0]])
    return _shaded(cam, corners, photo, gain, 2.0)


@pytest.mark.parametrize("reach", [0.0, 2.0])
def test_the_plates_own_cast_shadow_growing_beside_it_is_light_not_a_change(reach):
    """A lamp 27 deg above the bed: the plate's shadow grows 0.6 mm a layer. Without the cast-shadow test (reach 0)
    the scene channel reports it beside the print from layer 4 on (and keeps it, as a failure that stays); with
    reach 2 (the default) it reports nothing there. (A lamp that sways by a millimetre between photos is only partly
    forgiven: docs/evaluation/README.md, session 20.)"""
    tp = read_toolpath(PART_GCODE)
    cfg = recommended_config(PART_CONFIG)
    assert cfg.scene.shadow_reach == 2.0  # on unless a job turns it off (its price: docs/evaluation/README.md)
    cfg = cfg.model_copy(update={"scene": cfg.scene.model_copy(update={"shadow_reach": reach})})
    tv = cfg.topview.topview()
    cam = default_camera(tv)
    sim = PrintSimulator(tp, cam, tv, (), seed=5)
    pipe = LayerPipeline(tp, cam, cfg, bed_photo=sim.bed_photo())
    z = [float(tp.layers[i].z) for i in range(14)]
    photos = ((i, _cast_shadow(cam, 2.0 * z[i], sim.frame(i).photo)) for i in range(14))
    judged = list(judge_layers(pipe, PausePolicy(cfg.policy), photos))
    beside = [res.outside_anomalous_mm2 for res, _ in judged]
    if reach == 0.0:
        assert sum(a > 0 for a in beside) >= 3, beside
    else:
        assert all(res.status == "ok" for res, _ in judged)
        assert beside == [0.0] * 14, beside
        assert not any(d.stops for _, d in judged)


def _under_the_deck(cam, photo: np.ndarray, gain: float = 0.55) -> np.ndarray:
    """``photo`` with the window part's bridge deck's shade on the bed under it (x 91.5-98.5, y 97.5-102.5 mm for
    the part centred at (110, 100)), soft-edged: the whole opening darkens at once when the deck closes."""
    corners = np.array([[91.5, 97.5, 0.0], [98.5, 97.5, 0.0], [98.5, 102.5, 0.0], [91.5, 102.5, 0.0]])
    return _shaded(cam, corners, photo, gain, 1.5)


@pytest.mark.parametrize("reach", [0.0, 2.0])
def test_the_shade_under_a_new_bridge_deck_is_light_not_a_change(reach):
    """The window part's deck (layer 40, z 8-10 mm) closes over the bed between its pillars and the bed under it
    darkens to 0.55 over whole blocks at once, which the cast-shadow test alone takes for a clump that landed there
    (the 80 % cap). The deck is a roof of the part (material printed over air: cast_shadow.roof_area), so with
    shadow_reach 2 the shade under it is light and nothing is reported beside the print; without the cast-shadow
    test (0) it is reported and kept (Cycles photos: docs/evaluation/README.md, session 21)."""
    from layerwatch.simulate.parts import window_part

    cfg = recommended_config(PART_CONFIG)
    cfg = cfg.model_copy(update={"scene": cfg.scene.model_copy(update={"shadow_reach": reach})})
    tv = cfg.topview.topview()
    tp = window_part(center=(110.0, 100.0))
    assert tp.layers[40].z == pytest.approx(8.2)  # the deck's first layer
    cam = default_camera(tv)
    sim = PrintSimulator(tp, cam, tv, (), seed=5)
    pipe = LayerPipeline(tp, cam, cfg, bed_photo=sim.bed_photo())
    photos = ((i, _under_the_deck(cam, sim.frame(i).photo) if i >= 40 else sim.frame(i).photo) for i in range(36, 46))
    judged = list(judge_layers(pipe, PausePolicy(cfg.policy), photos))
    assert all(res.status == "ok" for res, _ in judged)
    beside = [res.outside_anomalous_mm2 for res, _ in judged]
    if reach == 0.0:
        assert all(a == 0 for a in beside[:4]) and all(a > 0 for a in beside[4:]), beside
    else:
        assert beside == [0.0] * 10, beside
        assert pipe.scene is not None and pipe.scene.roofs.any()


def test_the_plan_footprint_is_the_references_without_rendering():
    """What a baseline photo of a print under way takes the body from (``LayerPipeline.plan_footprint``) is the
    footprint of the layer's reference, pixel for pixel, and renders nothing."""
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    cam = default_camera(cfg.topview.topview())
    pipe = LayerPipeline(tp, cam, cfg)
    for i in (0, 7, 20, tp.n_layers - 1):
        done = pipe.renderer.done
        plan = pipe.plan_footprint(i)
        assert pipe.renderer.done == done  # the renderer's stack did not move
        want = pipe.footprint(i)
        np.testing.assert_array_equal(plan[0], want[0])
        assert plan[1:] == want[1:]


@pytest.mark.parametrize("join", [12, 20])
def test_a_monitor_that_joins_a_print_under_way_knows_the_part_already_printed(join):
    """A monitor (or a farm service) started while a clean print is under way takes its first photo, at layer
    ``join``, as the scene's baseline. That photo shows the part of layers 0..join: the scene model must know
    that body (its walls are not the scene beside the print, its floors are ledges), as a model that watched
    from layer 0 does. Before session 22 it knew only the layers after the join: the part's lower walls were
    scored as the bed beside it, and the clean print reported 14-95 mm^2 changed beside it and paused (layer
    24 when joined at 12, 22 when joined at 20)."""
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    sim = SimPrint(tp, cfg, None, 0, 1, keep=4)
    pipe = LayerPipeline(tp, sim.located, cfg)
    frames = ((i, sim.frame(i)) for i in range(join, min(join + 13, tp.n_layers)))
    judged = list(judge_layers(pipe, PausePolicy(cfg.policy), frames))
    assert all(res.status == "ok" for res, _ in judged)
    assert pipe.scene.baseline == "first photo"
    assert [res.outside_anomalous_mm2 for res, _ in judged] == [0.0] * len(judged)
    assert not any(d.stops for _, d in judged)


def _counted(fn, calls: list):
    """``fn`` that appends 1 to ``calls`` each time it is called."""
    def wrapped(*args, **kwargs):
        calls.append(1)
        return fn(*args, **kwargs)
    return wrapped


def test_a_frame_after_skipped_layers_takes_their_footprints_from_the_plan_with_the_same_verdicts():
    """Layers printed since the last accepted photo but never photographed (a skipped frame, a parked farm printer
    joining again) enter ``M`` by their footprints. Taken from the plan they are the references' masks, so every
    record is the one the rendered footprints gave; and the renderer, already at the photographed layer, is not
    started again from the first layer to render the skipped ones."""
    tp = read_toolpath(PART_GCODE)
    cfg = resolve_config(PART_CONFIG).config
    sim = SimPrint(tp, cfg, "spaghetti", 8, 2, keep=20)
    layers = [*range(0, 6), 10, 11, 12]
    out = {}
    for how in ("plan", "rendered"):
        pipe = LayerPipeline(tp, sim.located, cfg)
        if how == "rendered":
            pipe.plan_footprint = pipe.footprint  # type: ignore[method-assign]
        resets: list[int] = []
        pipe.renderer.reset = _counted(pipe.renderer.reset, resets)  # type: ignore[method-assign]
        records = [pipe.process(sim.frame(i), i).to_dict() for i in layers]
        for r in records:  # (the time taken differs: that is the point)
            r.pop("timings_ms", None)
            r["scene"].pop("ms", None)
        out[how] = (records, len(resets))
    assert out["plan"][0] == out["rendered"][0]
    assert out["plan"][1] == 0 < out["rendered"][1]
    assert any(r["outside_anomalous_mm2"] > 0 or r["anomaly_ratio"] > 0 for r in out["plan"][0][6:])  # (can fail)
