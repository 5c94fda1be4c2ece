"""Object labels of multi-object plates (issue 21): every labelled shared file, failures placed on every
object map to that object or fall back to a pause, never to another object."""

from itertools import combinations

import numpy as np
import pytest
from gcode_refs import _root

from layerwatch.analysis.result import Region
from layerwatch.gcode.objects import read_objects, without_objects
from layerwatch.gcode.reader import read_toolpath
from layerwatch.gcode.toolpath import part_mask

SHARED_DATA = _root.SHARED_DATA

#: the labelled multi-object plates among the shared files, their label style and object count
PLATES = {
    "prusaslicer-2.4.0a1_m486_arcwelder.gcode": ("m486", 4),
    "superslicer-2.3.56_arcwelder.gcode": ("slic3r", 4),
    "slic3r-1.3.1-dev_multi-object.gcode": ("slic3r", 4),
    "cura-4.10.0_m83_multi-object.gcode": ("cura", 4),
    "ideamaker-4.2.0_multi-object.gcode": ("ideamaker", 4),
    "bambustudio-2.4.0_single-layer.gcode": ("orca", 3),
}


def _plate(name):
    path = SHARED_DATA / "gcode" / name
    if not path.is_file():
        pytest.skip("shared data absent")
    tp = read_toolpath(path)
    return path, tp, read_objects(path, tp)


def _box_region(cx, cy, h):
    return Region(4 * h * h, (cx - h, cy - h, cx + h, cy + h), (cx, cy), 1, 0.2)


@pytest.mark.parametrize("name", sorted(PLATES))
def test_plate_objects_are_found_and_disjoint(name):
    _, tp, om = _plate(name)
    style, n = PLATES[name]
    assert om.style == style and len(om.objects) == n and om.labelled
    # the part's segments are labelled (skirt, brim and purge lines are not objects)
    assert (om.segment_object[part_mask(tp.feature)] >= 0).mean() > 0.85  # ideaMaker: the raft is no object
    for a, b in combinations(om.objects, 2):  # all-at-once plates: objects never overlap on the bed
        ax0, ay0, ax1, ay1 = a.bbox_mm
        bx0, by0, bx1, by1 = b.bbox_mm
        assert ax1 < bx0 or bx1 < ax0 or ay1 < by0 or by1 < ay0, (a.name, b.name)


def test_m486_ids_and_comment_labels_agree():
    path, tp, om = _plate("prusaslicer-2.4.0a1_m486_arcwelder.gcode")
    comments = read_objects(path, tp, style="slic3r")
    assert [o.firmware_id for o in om.objects] == [0, 1, 2, 3]
    names = {o.index: o.name for o in comments.objects}
    both = (om.segment_object >= 0) & (comments.segment_object >= 0)
    assert both.mean() > 0.95
    assert all(om.objects[i].name == names[j] for i, j in
               set(zip(om.segment_object[both].tolist(), comments.segment_object[both].tolist(), strict=True)))


def test_no_wrong_object_over_failures_on_every_object_of_every_plate():
    """Failures (2-8 mm boxes) centred on printed points of each object at 20/50/80 % of its layers."""
    rng = np.random.default_rng(21)
    correct = fallback = wrong = 0
    for name in PLATES:
        _, tp, om = _plate(name)
        for obj in om.objects:
            layers = sorted({tp.layers[i].index for i in range(tp.n_layers)
                             if (om.segment_object[tp.layer_slice(i)] == obj.index).any()})
            for q in (0.2, 0.5, 0.8):
                layer = layers[int(q * (len(layers) - 1))]
                sl = tp.layer_slice(layer)
                idx = np.flatnonzero(om.segment_object[sl] == obj.index) + sl.start
                for k in rng.choice(idx, size=min(8, len(idx)), replace=False):
                    cx, cy = (tp.start[k] + tp.end[k]) / 2
                    got = om.locate(tp, [_box_region(cx, cy, rng.uniform(1.0, 4.0))], layer).single
                    if got is None:
                        fallback += 1
                    elif got == obj.index:
                        correct += 1
                    else:
                        wrong += 1
    print(f"object cancel: {correct} correct, {fallback} paused instead, {wrong} wrong")
    assert wrong == 0 and correct + fallback > 400 and correct > fallback


def test_failures_between_objects_or_beside_them_pause_instead():
    _, tp, om = _plate("slic3r-1.3.1-dev_multi-object.gcode")
    a, b = om.objects[0], om.objects[2]  # cube copy 0 at y 81..86, cylinder at y 92..97
    between = om.locate(tp, [Region(50, (97, 84, 103, 94), (100, 89), 5, 0.2)], tp.n_layers - 1)
    assert between.single is None and "spans" in between.reason and set(between.objects) == {a.index, b.index}
    beside = om.locate(tp, [Region(9, (20, 20, 23, 23), (21.5, 21.5), 2, 0.2)], tp.n_layers - 1)
    assert beside.single is None and "touches no object" in beside.reason
    path = SHARED_DATA / "gcode" / "prusaslicer-2.6.0_mini-ascii.gcode"
    single = read_objects(path, tp2 := read_toolpath(path))
    one = single.locate(tp2, [Region(9, (85, 85, 88, 88), (86, 86), 2, 0.2)], 3)
    assert not single.labelled and one.single is None and "labels no objects" in one.reason


def test_without_objects_drops_the_cancelled_object_above_the_layer_only():
    _, tp, om = _plate("cura-4.10.0_m83_multi-object.gcode")
    cut = 10
    out = without_objects(tp, om, {1: cut})
    assert out.n_layers == tp.n_layers
    for i in range(tp.n_layers):
        before = om.segment_object[tp.layer_slice(i)]
        assert out.layers[i].n_segments == tp.layers[i].n_segments - (int((before == 1).sum()) if i > cut else 0)
    kept = np.isin(out.line, tp.line[om.segment_object == 1])
    assert kept.any() and out.z[kept].max() <= tp.layers[cut].z + 1e-9
