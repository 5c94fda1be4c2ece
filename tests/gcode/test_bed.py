"""The bed a file states, and the park spot chosen on it."""

from __future__ import annotations

import pytest
from gcode_refs import shared_gcode_files

from layerwatch.errors import ConfigError
from layerwatch.gcode.bed import bed_from_gcode, choose_park, parse_bed
from layerwatch.gcode.reader import load_bytes

FILES = {p.name: p for p in shared_gcode_files()}

STATED = {  # what each file's own header says (see shared/data/PROVENANCE.md and the files)
    "prusaslicer-2.7.4_spiral-vase.gcode": ((5, 0, 215, 220), 250, "bed_shape"),
    "prusaslicer-2.9.6_xl2is-heatshrink12-meatpack.bgcode": ((0, 0, 360, 360), 360, "bed_shape"),
    "orcaslicer-2.3.1_bambu-a1-gridfinity.gcode": ((0, 0, 256, 256), 256, "printable_area"),
    "bambustudio-2.1.1_plate.gcode": ((0, 0, 180, 180), 180, "printable_area"),
    "kisslicer-2.0.6.gcode": ((0, 0, 100, 100), 100, "bed_size_x_mm/bed_size_y_mm"),
    "icesl-2021.gcode": ((0, 0, 120, 120), None, "bed_size_x_mm/bed_size_y_mm"),
    "kirimoto-3.0.gcode": ((0, 0, 300, 300), None, "Kiri:Moto 'Bed'"),
    "cura-4.10.0_m83_multi-object.gcode": None,
}


@pytest.mark.parametrize("name", list(STATED))
def test_bed_stated_by_shared_files(name):
    if name not in FILES:
        pytest.skip("shared data absent")
    bed = bed_from_gcode(load_bytes(FILES[name])[0])
    if STATED[name] is None:
        assert bed is None
        return
    box, height, source = STATED[name]
    assert bed.bounds == box and bed.max_z_mm == height and bed.source == source


def test_cura_machine_settings_with_centre_origin():
    footer = (b';SETTING_3 {"global_quality": "[general]\\\\nversion = 4\\\\n[values]\\\\nmachine_width = 235\\\\n'
              b'machine_depth = 220\\\\nmachine_height = 250\\\\nmachine_center_is_zero = True\\\\n"}\n')
    bed = bed_from_gcode(b";FLAVOR:Marlin\nG1 X0 Y0\n" + footer)
    assert bed.bounds == (-117.5, -110.0, 117.5, 110.0) and bed.max_z_mm == 250.0


def test_polygon_bed_contains_and_park():
    delta = parse_bed(";".join(f"{100 * c:.3f},{100 * s:.3f}" for c, s in
                               [(1, 0), (0.5, 0.866), (-0.5, 0.866), (-1, 0), (-0.5, -0.866), (0.5, -0.866)]))
    x, y = choose_park(delta, (-10.0, -10.0, 10.0, 10.0))
    assert delta.contains(x, y, margin=5.0) and (x * x + y * y) ** 0.5 > 80
    assert not delta.contains(float("nan"), 0.0) and not delta.contains(100.0, 50.0)
    with pytest.raises(ConfigError, match="too small"):
        choose_park(parse_bed("8x8"), (0, 0, 1, 1))
