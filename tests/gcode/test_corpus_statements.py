"""Every real slicer file in ../shared/data/gcode is read as its slicer meant it: the expected
values come from the file's OWN statements (layer count, filament used, first-layer box and
height, print box, max Z, generator), never from a table of file names.

Where a file states nothing the check is skipped for that file and the test says so in its
report (``-rs``). Two files state a filament length that their own E words contradict; those
are listed in ``KNOWN_DISAGREEMENTS`` with the measured reason, and for them the test asserts
that the reader *reports* the disagreement instead of agreeing.
"""

from __future__ import annotations

import re

import pytest
from gcode_refs import shared_gcode_files

from layerwatch.gcode import read_toolpath
from layerwatch.gcode.reader import load_bytes
from layerwatch.gcode.statements import compare, read_statements

FILES = shared_gcode_files()
IDS = [p.name for p in FILES]
BOX_TOL_MM = 2.0

#: file -> why its stated filament length is not what its E words say (measured, see each reason)
KNOWN_DISAGREEMENTS = {
    # the print's wall moves all carry E0 (e.g. 'G1 X63.133 Y164.471 E0'): the statement (75.74 mm)
    # is the slicer's model of the print, which the written moves do not extrude
    "bambustudio-2.4.0_single-layer.gcode": "print moves written with E0",
    # states 'Material#1 Used: 422.7'; E words 479.4 mm, fed with M221 T0 S94 450.7 mm;
    # 479.4 * 0.94**2 = 423.6: ideaMaker applies its 94 % compensation twice in the statement
    "ideamaker-4.2.0_multi-object.gcode": "statement applies the 94 % compensation twice",
}


#: file -> why its stated first-layer height is not where its first layer is printed
KNOWN_FIRST_LAYER = {
    # states 'z_layer_height_first_layer_mm : 0.3' (a setting) but prints layer 0 at 'G1 Z0.120' (line 404)
    "icesl-2021.gcode": "first-layer setting not applied by IceSL",
}


@pytest.fixture(scope="module")
def parsed():
    cache = {}

    def get(path):
        if path not in cache:
            cache[path] = read_toolpath(path)
        return cache[path]

    return get


def _statements(path):
    return read_statements(load_bytes(path)[0])


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_generator_named(path, parsed):
    tp = parsed(path)
    if tp.n_segments == 0:  # a CNC file (no extrusion): described by its header line, not "unknown"
        assert tp.generator.name is None and tp.generator.header
        assert "unknown" not in tp.generator.describe()
        return
    assert tp.generator.name, tp.generator
    assert tp.generator.describe() != "unknown"


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_layer_count_as_stated(path, parsed):
    st = _statements(path)
    if st.layer_count is None:
        pytest.skip(f"{path.name} states no layer count")
    assert abs(parsed(path).n_layers - st.layer_count) <= 1


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_filament_as_stated(path, parsed):
    st = _statements(path)
    if st.filament_mm is None:
        pytest.skip(f"{path.name} states no filament length")
    tp = parsed(path)
    found = compare(st, layers=tp.n_layers, filament_mm=tp.filament_commanded_mm, max_z=None,
                    first_layer_box=None)
    if path.name in KNOWN_DISAGREEMENTS:
        assert any(d.field.startswith("filament") for d in found), KNOWN_DISAGREEMENTS[path.name]
        return
    # slicers state what their E words ask for; M221 is the printer's (checked below)
    assert tp.filament_commanded_mm == pytest.approx(st.filament_mm, rel=0.02)
    assert not found


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_filament_volume_as_stated(path, parsed):
    st = _statements(path)
    if st.filament_cm3 is None:
        pytest.skip(f"{path.name} states no filament volume")
    tp = parsed(path)
    cm3 = tp.filament_commanded_mm * tp.filament_area_mm2 / 1000.0
    found = compare(st, layers=tp.n_layers, filament_mm=tp.filament_commanded_mm, max_z=None,
                    first_layer_box=None, filament_cm3=cm3)
    if path.name in KNOWN_DISAGREEMENTS:
        assert any(d.field == "filament (cm3)" for d in found), KNOWN_DISAGREEMENTS[path.name]
        return
    assert cm3 == pytest.approx(st.filament_cm3, rel=0.02, abs=0.006)  # statements round to 0.01 cm^3
    assert not found


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_m221_applied_to_what_is_fed(path, parsed):
    text = load_bytes(path)[0]
    flows = [float(v) for v in re.findall(rb"(?m)^M221 (?:T0 )?S(\d+(?:\.\d+)?)", text)]
    printing = [f for f in flows if f != 100.0]
    if not printing:
        pytest.skip(f"{path.name} sets no flow other than 100 %")
    tp = parsed(path)
    # each flow value set before the print applies to the whole print (reset to 100 at the end)
    assert len(set(printing)) == 1
    ratio = tp.extrusion_mm / tp.filament_commanded_mm
    assert ratio == pytest.approx(printing[0] / 100.0, rel=0.01)


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_first_layer_height_as_stated(path, parsed):
    st = _statements(path)
    if st.first_layer_height is None:
        pytest.skip(f"{path.name} states no first-layer height")
    tp = parsed(path)
    found = compare(st, layers=tp.n_layers, filament_mm=tp.filament_commanded_mm, max_z=None,
                    first_layer_box=None, first_layer_z=tp.layers[0].z)
    if path.name in KNOWN_FIRST_LAYER:
        assert any(d.field.startswith("first layer Z") for d in found), KNOWN_FIRST_LAYER[path.name]
        return
    assert tp.layers[0].z == pytest.approx(st.first_layer_height, abs=0.05)
    assert not [d for d in found if d.field.startswith("first layer Z")]


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_first_layer_inside_stated_box(path, parsed):
    st = _statements(path)
    if st.first_layer_box is None:
        pytest.skip(f"{path.name} states no first-layer box (M555, G29 A1)")
    x0, y0, x1, y1 = parsed(path).layers[0].bounds
    bx0, by0, bx1, by1 = st.first_layer_box
    assert bx0 - BOX_TOL_MM <= x0 and by0 - BOX_TOL_MM <= y0, (st.first_layer_box_source, (x0, y0))
    assert x1 <= bx1 + BOX_TOL_MM and y1 <= by1 + BOX_TOL_MM, (st.first_layer_box_source, (x1, y1))


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_part_inside_stated_print_box(path, parsed):
    st = _statements(path)
    if st.print_box is None:
        pytest.skip(f"{path.name} states no print box")
    x0, y0, x1, y1 = parsed(path).bounds
    bx0, by0, bx1, by1 = st.print_box
    assert bx0 - BOX_TOL_MM <= x0 and by0 - BOX_TOL_MM <= y0 and x1 <= bx1 + BOX_TOL_MM and y1 <= by1 + BOX_TOL_MM


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_max_z_as_stated(path, parsed):
    st = _statements(path)
    if st.max_z is None:
        pytest.skip(f"{path.name} states no max Z")
    tp = parsed(path)
    top = tp.layers[-1].z
    # Cura's MAXZ includes the lift after the last layer: the top layer lies up to one layer below it
    below = max((st.layer_height or tp.layers[-1].height) + 0.05, 0.02 * st.max_z)
    assert st.max_z - below <= top <= st.max_z + 0.05
    assert not compare(st, layers=tp.n_layers, filament_mm=st.filament_mm or 0.0, max_z=top, first_layer_box=None)


def test_bambu_volume_statement_is_mm3():
    """Bambu Studio writes mm^3 under 'total filament volume [cm^3]'; read as what it is."""
    bambu = [p for p in FILES if p.name.startswith("bambustudio")]
    if not bambu:
        pytest.skip("shared data absent")
    for path in bambu:
        st = _statements(path)
        assert st.filament_cm3 == pytest.approx(st.filament_volume_stated / 1000.0)
        assert any("mm^3" in n for n in st.notes)


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_non_part_lines_kept_for_references_but_not_in_bounds(path, parsed):
    """Purge lines, skirts, brims and wipe towers stay in the toolpath (references draw them:
    the camera sees that plastic) with their own feature codes; layer 0's part box leaves them out."""
    import numpy as np

    from layerwatch.gcode.toolpath import part_mask

    st = _statements(path)
    if st.first_layer_box is None:
        pytest.skip(f"{path.name} states no first-layer box (M555, G29 A1)")
    tp = parsed(path)
    sl = tp.layer_slice(0)
    pts = np.concatenate([tp.start[sl], tp.end[sl]])
    bx0, by0, bx1, by1 = st.first_layer_box
    outside = ((pts[:, 0] < bx0 - BOX_TOL_MM) | (pts[:, 0] > bx1 + BOX_TOL_MM)
               | (pts[:, 1] < by0 - BOX_TOL_MM) | (pts[:, 1] > by1 + BOX_TOL_MM))
    assert outside.any(), "layer 0 draws no purge/skirt outside the part box"
    not_part = ~np.concatenate([part_mask(tp.feature[sl])] * 2)
    assert not_part[outside].all()  # everything drawn outside the stated box is classified as not-part
