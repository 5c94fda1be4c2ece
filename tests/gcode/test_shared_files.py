"""Every real slicer file in ../shared/data/gcode parses; layer counts match the slicer's tags;
the post-processor's output re-parses to the same layers and per-layer extrusion."""

from __future__ import annotations

import re

import numpy as np
import pytest
from gcode_refs import reference_extrusion, shared_gcode_files

from layerwatch.gcode import read_toolpath
from layerwatch.gcode.bed import bed_from_gcode, parse_bed
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.gcode.reader import load_bytes
from layerwatch.gcode.settings import PrinterProfile, SnapshotSettings

FILES = shared_gcode_files()
GCODE = [p for p in FILES if p.suffix == ".gcode"]
IDS = [p.name for p in FILES]

# independent tag counters (line-anchored regexes over the whole text)
TAG_COUNTERS = {
    "tags:prusaslicer": lambda t: len(re.findall(r"(?m)^;LAYER_CHANGE\s*$", t)),
    "tags:cura": lambda t: len(set(re.findall(r"(?m)^;LAYER:(-?\d+)\s*$", t))),
    "tags:simplify3d": lambda t: len(re.findall(r"(?m)^; layer \d+, Z = ", t)),
    "tags:kisslicer": lambda t: len(re.findall(r"(?m)^; BEGIN_LAYER_OBJECT z=", t)),
}


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_parses(path):
    tp = read_toolpath(path)
    if "plasma" in path.name:  # a CNC file: no extrusion, said in a warning
        assert tp.n_layers == 0 and any("no extruding" in w for w in tp.warnings)
        return
    stated = tp.statements.layer_count  # the Bambu 2.4 file states (and is) a single layer
    assert tp.n_layers >= (5 if stated is None else min(stated, 5))
    assert tp.extrusion_mm > 10
    assert np.all(tp.e > 0)
    assert sum(lay.n_segments for lay in tp.layers) == tp.n_segments
    assert all(lay.line_start < lay.line_stop for lay in tp.layers)
    med = float(np.median(tp.width))
    assert 0.2 < med < 3.0, med
    if tp.detection.startswith("tags:") and tp.detection in TAG_COUNTERS:
        text = load_bytes(path)[0].decode("latin-1")
        assert tp.n_layers == TAG_COUNTERS[tp.detection](text)


def test_detection_methods_cover_dialects():
    if not FILES:
        pytest.skip("shared data absent")
    det = {p.name: read_toolpath(p).detection for p in GCODE}
    assert det["fullcontrol_ripple-vase_g91.gcode"] == "spiral"
    assert det["prusaslicer-2.7.4_spiral-vase.gcode"] == "tags:prusaslicer"
    assert det["cura-4.10.0_m83_multi-object.gcode"] == "tags:cura"
    assert det["simplify3d-4.1.2_zlift.gcode"] == "tags:simplify3d"
    assert det["slic3r-1.2.9_reprapfirmware.gcode"] == "z"


@pytest.mark.parametrize(
    "name", ["cura-4.10.0_m83_multi-object.gcode", "slic3r-1.2.9_reprapfirmware.gcode", "simplify3d-4.1.2_zlift.gcode"]
)
def test_extrusion_matches_gcodeparser_reference(name):
    path = next((p for p in GCODE if p.name == name), None)
    if path is None:
        pytest.skip("shared data absent")
    tp = read_toolpath(path)
    total, count = reference_extrusion(path.read_text(errors="replace"))
    assert tp.n_segments == count
    assert tp.extrusion_mm == pytest.approx(total, rel=1e-9)


@pytest.mark.parametrize("path", GCODE, ids=[p.name for p in GCODE])
def test_postprocess_round_trip(path):
    data = path.read_bytes()
    before = read_toolpath(data)
    profile = ["klipper", "octoprint", "paper", "m240", "timelapse"][len(path.name) % 5]
    bed = None
    if bed_from_gcode(data) is None and before.n_layers:  # no bed stated: one around the print (prepare won't guess)
        x0, y0, x1, y1 = before.bounds
        bed = parse_bed(f"{x0 - 20},{y0 - 20};{x1 + 20},{y0 - 20};{x1 + 20},{y1 + 20};{x0 - 20},{y1 + 20}")
    out = insert_snapshots(data, SnapshotSettings(profile=profile), PrinterProfile(), bed=bed)
    after = read_toolpath(out)
    assert after.n_layers == before.n_layers
    np.testing.assert_allclose([lay.z for lay in after.layers], [lay.z for lay in before.layers])
    np.testing.assert_allclose(
        [lay.extrusion_mm for lay in after.layers],
        [lay.extrusion_mm for lay in before.layers],
        rtol=1e-12,
        atol=1e-9,
    )
    assert out.count(b"; layerwatch snapshot block end") == before.n_layers


def test_bgcode_matches_its_ascii_twin():
    """heatshrink + MeatPack .bgcode decodes to the same toolpath as PrusaSlicer's ASCII export."""
    pair = {p.suffix: p for p in FILES if p.name.startswith("prusaslicer-2.8.1_mini-cube")}
    if len(pair) < 2:
        pytest.skip("shared data absent")
    a, b = read_toolpath(pair[".bgcode"]), read_toolpath(pair[".gcode"])
    assert a.n_layers == b.n_layers and a.detection == b.detection
    np.testing.assert_allclose(a.start, b.start)
    np.testing.assert_allclose(a.e, b.e)
    assert (a.feature == b.feature).all()
    assert a.slicer == b.slicer == "PrusaSlicer"


def test_feature_types_named_by_slicers():
    from layerwatch.gcode.toolpath import FEATURES

    want = {
        "prusaslicer-2.8.1_mini-cube_ascii.gcode": {"external_perimeter", "perimeter", "solid_infill", "infill"},
        "cura-4.10.0_m83_multi-object.gcode": {"external_perimeter", "perimeter", "solid_infill"},
        "simplify3d-4.1.2_zlift.gcode": {"external_perimeter", "perimeter", "infill", "solid_infill"},
        "kisslicer-2.0.6.gcode": {"external_perimeter", "perimeter"},
    }
    files = {p.name: p for p in GCODE}
    if not files:
        pytest.skip("shared data absent")
    for name, names in want.items():
        got = {FEATURES[c] for c in np.unique(read_toolpath(files[name]).feature)}
        assert names <= got, (name, got)
