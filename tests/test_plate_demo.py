"""``layerwatch demo --plate`` (issue 21): four objects, one fails, it alone is cancelled, the rest finish."""

import pytest

from layerwatch.cli import main
from layerwatch.evaluate.plate_demo import run_plate_demo
from layerwatch.examples import PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.objects import read_objects
from layerwatch.gcode.toolpath import part_mask
from layerwatch.simulate.plate import PLATE_NAMES, plate_gcode


def test_plate_is_four_labelled_disjoint_copies_of_the_part():
    part = read_toolpath(PART_GCODE)
    data = plate_gcode(part)
    tp = read_toolpath(data)
    om = read_objects(data, tp)
    assert tp.n_layers == part.n_layers and om.style == "exclude_object"
    assert [o.name for o in om.objects] == list(PLATE_NAMES) and (om.segment_object >= 0).all()
    boxes = [o.bbox_mm for o in om.objects]
    assert all(a[2] < b[0] or b[2] < a[0] or a[3] < b[1] or b[3] < a[1]
               for i, a in enumerate(boxes) for b in boxes[i + 1:])
    assert tp.extrusion_mm == pytest.approx(4 * 0.5 * part.e[part_mask(part.feature)].sum(), rel=1e-3)  # no skirt


@pytest.mark.slow
def test_plate_demo_cancels_the_failed_object_and_the_rest_finish(tmp_path):
    res = run_plate_demo(tmp_path, failed=1, onset=12)
    assert [(a, res.failed) for _, a, _ in res.stops] == [("cancel_object", "part_B")]
    assert list(res.cancelled) == ["part_B"] and res.cancelled["part_B"] <= res.onset + 2
    assert res.layers == res.total_layers  # the other three printed to the end
    assert not [a for a in res.later_alarms if a[3]]  # nothing more about the cancelled object
    assert (tmp_path / "summary.md").is_file() and (tmp_path / "plate.gcode").is_file()
    assert res.host_lines[0] == "EXCLUDE_OBJECT NAME=PART_B"  # Klipper keeps names upper case


def test_plate_demo_refuses_failures_it_cannot_place_on_one_object(tmp_path, capsys):
    assert main(["demo", "--plate", "--failure", "layer_shift", "-o", str(tmp_path)]) == 2
    err = capsys.readouterr()
    assert "--failure spaghetti or foreign_body" in err.err + err.out
