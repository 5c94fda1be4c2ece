"""A printer's job geometry kept between its jobs (pipeline/job_geometry.py): the same values as built afresh."""

from __future__ import annotations

import numpy as np
import pytest

from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.farm.remote import GEOMETRY, JobContext
from layerwatch.farm.simcam import SimPrint
from layerwatch.gcode import read_toolpath
from layerwatch.pipeline.config import resolve_config
from layerwatch.pipeline.job_geometry import JobGeometry, PrinterGeometries
from layerwatch.pipeline.scene import SceneModel
from layerwatch.pipeline.step import LayerPipeline


@pytest.fixture(scope="module")
def job():
    tp, cfg = read_toolpath(PART_GCODE), resolve_config(PART_CONFIG).config
    sim = SimPrint(tp, cfg, "spaghetti", 6, 1, keep=16)
    return tp, cfg, sim


def _same(a, b, where: str) -> None:
    """``a`` equals ``b``: arrays bit for bit (dtype and shape too), tuples item by item, anything else by ``==``."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        assert isinstance(a, np.ndarray) and isinstance(b, np.ndarray), where
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), where
    elif isinstance(a, tuple) and isinstance(b, tuple):
        assert len(a) == len(b), where
        for k, (u, v) in enumerate(zip(a, b, strict=True)):
            _same(u, v, f"{where}[{k}]")
    else:
        assert a == b, where


def _record(res) -> dict:
    d = res.to_dict()
    d.pop("timings_ms")
    if d.get("scene"):
        d["scene"].pop("ms")
    return d


def test_a_printers_next_job_from_its_kept_geometry_holds_and_records_what_a_new_one_does(job):
    tp, cfg, sim = job
    geo = JobGeometry()
    first = LayerPipeline(tp, sim.located, cfg, geometry=geo)  # builds and keeps the scene model's view maps
    first.process(sim.frame(0), 0)  # the checks' box maps are made by the first photo's checks
    assert (geo.misses, geo.hits, len(geo)) == (2, 0, 2)
    bed = sim.frame(0)  # a bed photo of the new job: the scene model is reset with it, as the constructor does
    kept = LayerPipeline(tp, sim.located, cfg, geometry=geo, bed_photo=bed)
    new = LayerPipeline(tp, sim.located, cfg, bed_photo=bed)
    assert geo.hits == 1
    assert kept.scene is not None and new.scene is not None
    assert vars(kept.scene).keys() == vars(new.scene).keys()
    for name, value in vars(new.scene).items():
        if name not in ("camera", "topview", "settings"):  # the same objects' values (the job's own)
            _same(getattr(kept.scene, name), value, f"scene.{name}")
    beside = 0.0
    for i in range(14):  # the spaghetti starts at layer 6: the scene channel finds it
        photo = sim.frame(i)
        a, b = kept.process(photo, i), new.process(photo, i)
        assert _record(a) == _record(b), i
        beside += _record(a)["outside_anomalous_mm2"]
        _same(kept.checks.box, new.checks.box, "checks.box")
        _same(kept.checks.maps, new.checks.maps, "checks.maps")
    assert geo.hits == 2  # the checks' maps came from the first job
    assert beside > 0  # the scene channel saw the strands


def test_kept_arrays_are_read_only_and_each_reach_has_its_own(job):
    tp, cfg, sim = job
    geo = JobGeometry()
    tv = cfg.topview.topview()
    one = geo.scene(sim.located, tv, cfg.scene, None, reach_mm=(80.0, 80.0, 120.0, 120.0), top_z_mm=6.0)
    other = geo.scene(sim.located, tv, cfg.scene, None, reach_mm=(90.0, 90.0, 110.0, 110.0), top_z_mm=6.0)
    fresh = SceneModel(sim.located, tv, cfg.scene, reach_mm=(90.0, 90.0, 110.0, 110.0), top_z_mm=6.0)
    assert geo.misses == 2 and geo.hits == 0
    assert one.reach_box != other.reach_box
    _same(other.reach_box, fresh.reach_box, "reach_box")
    _same(other.maps, fresh.maps, "maps")
    with pytest.raises(ValueError, match="read-only"):
        other.maps[0][0, 0, 0] = 0.0
    other.body[...] = True  # the job's own state is its own
    again = geo.scene(sim.located, tv, cfg.scene, None, reach_mm=(90.0, 90.0, 110.0, 110.0), top_z_mm=6.0)
    assert geo.hits == 1 and not again.body.any()


def test_printers_keep_their_own_geometry_and_the_least_recently_used_go():
    geos = PrinterGeometries(max_printers=2)
    a = geos.of("a")
    assert geos.of("a") is a and geos.of("b") is not a
    geos.of("c")  # "a" was used before "b"... then "b": "a" is the oldest
    assert len(geos) == 2 and geos.of("a") is not a
    kept = JobGeometry(max_entries=1)
    assert kept.get("x", lambda: np.zeros(2)) is kept.get("x", lambda: np.ones(2))
    kept.get("y", lambda: np.ones(2))
    assert len(kept) == 1 and kept.get("x", lambda: np.ones(2))[0] == 1.0
    with pytest.raises(ValueError):
        JobGeometry(max_entries=0)


def test_a_farm_jobs_pipeline_takes_its_printers_geometry(job):
    tp, cfg, sim = job
    GEOMETRY.clear()
    JobContext("p/1", tp, sim.located, cfg, printer="p").pipeline()
    JobContext("q/1", tp, sim.located, cfg, printer="q").pipeline()  # another printer: not given p's
    JobContext("anon/1", tp, sim.located, cfg).pipeline()  # no printer: nothing kept
    assert len(GEOMETRY) == 2 and GEOMETRY.of("p").misses == 1 and GEOMETRY.of("q").misses == 1
    JobContext("p/2", tp, sim.located, cfg, printer="p").pipeline()
    assert GEOMETRY.of("p").hits == 1 and GEOMETRY.of("q").hits == 0
    GEOMETRY.clear()
