"""Failure truth per type on small synthetic scenes: what the camera sees, hidden pixels removed, staying failures kept."""

from __future__ import annotations

import numpy as np

from layerwatch.geometry.topview import TopView
from layerwatch.simulate import Failure, PrintSimulator
from layerwatch.simulate import truth as tr

GRID = TopView(8.0, 60.0, 60.0, (0.0, 0.0))
TOP = TopView(5.0, 60.0, 60.0, (0.0, 0.0))
#: camera 60 mm behind the bed centre (-y) and 60 mm up: looks towards +y at 45 degrees
C = np.array([0.0, -60.0, 60.0])


def _box(h: np.ndarray, x0: float, y0: float, x1: float, y1: float, z: float) -> np.ndarray:
    xy = GRID.to_mm(np.stack(np.meshgrid(np.arange(h.shape[1]), np.arange(h.shape[0])), -1).astype(float))
    inside = (xy[..., 0] >= x0) & (xy[..., 0] <= x1) & (xy[..., 1] >= y0) & (xy[..., 1] <= y1)
    out = h.copy()
    out[inside] = np.maximum(out[inside], z)
    return out


def _px(mask: np.ndarray) -> np.ndarray:
    """Bed mm of the top-view pixels in ``mask`` (N, 2)."""
    v, u = np.nonzero(mask)
    return TOP.to_mm(np.stack([u, v], -1).astype(float)).reshape(-1, 2)


def test_first_hit_sees_the_box_top_and_the_bed():
    h = _box(np.zeros(GRID.shape, np.float32), -5, -5, 5, 5, 10.0)
    hits = tr.first_hit(tr.Sight(C, TOP, GRID, 10.0), h, None)
    uv = np.round(TOP.to_px(np.array([[0.0, 0.0], [20.0, 20.0]]))).astype(int)
    assert abs(hits.z[uv[0, 1], uv[0, 0]] - 10.0) < 0.2  # the top, on the top view's own plane
    assert hits.z[uv[1, 1], uv[1, 0]] == 0.0 and hits.cell[uv[1, 1], uv[1, 0], 0] == -1  # the bed


def test_an_object_behind_a_tall_part_is_hidden():
    """A block on the bed behind a 12 mm part (seen from the camera) is truth only where it shows."""
    part = _box(np.zeros(GRID.shape, np.float32), -10, -10, 10, 0, 12.0)
    sight = tr.Sight(C, TOP, GRID, 12.0)
    behind = _box(part, -4, 1, 4, 5, 3.0)  # 3 mm tall, just behind the part's far wall
    beside = _box(part, 14, -14, 22, -10, 3.0)  # in the open
    hidden = tr.raised_object(sight, behind, None, part)
    seen = tr.raised_object(sight, beside, None, part)
    assert seen.sum() > 8 * 4 * TOP.px_per_mm**2 * 0.8  # the whole top at least, and its near side
    assert hidden.sum() == 0  # 3 mm tall, 1 mm behind a 12 mm wall, the camera 45 degrees up: out of sight
    taller = _box(part, -4, 1, 4, 5, 20.0)  # pokes 8 mm over the part: its top part shows, not its foot
    some = tr.raised_object(sight, taller, None, part)
    assert some.sum() > 0
    # each pixel of its truth sees the object, not the part: its ray passes over the part's top
    assert some.sum() < tr.raised_object(tr.Sight(C, TOP, GRID, 12.0), _box(np.zeros(GRID.shape, np.float32),
                                         -4, 1, 4, 5, 20.0), None, np.zeros(GRID.shape, np.float32)).sum()


def test_a_hole_counts_while_seen_and_not_once_covered():
    lh = 0.3
    part = _box(np.zeros(GRID.shape, np.float32), -15, -15, 15, 15, 3.0)
    hole = _box(np.zeros(GRID.shape, np.float32), -15, -15, 15, 15, 3.0 - 2 * lh)
    rim = part.copy()
    ring = _box(np.zeros(GRID.shape, np.float32), -4, -4, 4, 4, 1.0) > 0
    hole = np.where(ring, hole, part)  # an 8 mm pit two layers deep
    sight = tr.Sight(C, TOP, GRID, 3.0)
    seen = tr.patch(sight, hole, None, rim, 0.5 * lh)
    xy = _px(seen)
    assert len(xy) > 0.8 * 64 * TOP.px_per_mm**2  # nearly all of the pit (its near rim hides 0.6 mm)
    assert np.abs(xy).max() < 4.0 + 2 / TOP.px_per_mm  # and nothing beyond it
    covered = tr.patch(sight, _box(hole, -4, -4, 4, 0, 3.0), None, rim, 0.5 * lh)  # a later layer closes half
    assert 0.3 * len(xy) < covered.sum() < 0.7 * len(xy)


def test_a_deep_narrow_slot_shows_only_its_far_wall():
    """The bottom of a 1 mm slot 6 mm deep is out of sight at 45 degrees: only the far wall's top is truth."""
    part = _box(np.zeros(GRID.shape, np.float32), -15, -15, 15, 15, 6.0)
    slot = np.where(_box(np.zeros(GRID.shape, np.float32), -10, -0.5, 10, 0.5, 1.0) > 0, 0.0, part).astype(np.float32)
    seen = tr.patch(tr.Sight(C, TOP, GRID, 6.0), slot, None, part, 0.15)
    xy = _px(seen)
    assert len(xy) > 0
    assert np.abs(xy[:, 1]).max() <= 0.5 + 1.5 / TOP.px_per_mm  # the slot's own pixels, nothing beside it
    assert len(xy) < 20 * 1.0 * TOP.px_per_mm**2  # and at most its opening


def test_detachment_truth_is_the_moved_part_as_seen_and_the_place_it_left():
    plan = _box(np.zeros(GRID.shape, np.float32), -10, -10, 10, 10, 5.0)
    h = _box(np.zeros(GRID.shape, np.float32), -6, -10, 14, 10, 5.0)  # moved 4 mm along +x
    sight = tr.Sight(C, TOP, GRID, 5.0)
    out = tr.detachment(sight, h, None, h > 0, plan, None, 0.15)
    xy = _px(out)
    assert (xy[:, 0] < -6).sum() > 0.8 * 4 * 20 * TOP.px_per_mm**2  # the vacated band
    top_of_moved = (xy[:, 0] > -5) & (xy[:, 0] < 13) & (np.abs(xy[:, 1]) < 9)
    assert top_of_moved.sum() > 0.9 * 18 * 18 * TOP.px_per_mm**2  # the whole moved top: all of it is off
    assert xy[:, 1].max() < 10.5  # the far wall is hidden: nothing beyond the top's far edge


def test_layer_shift_truth_is_the_two_bands_not_the_overlap():
    lh = 0.3
    below = _box(np.zeros(GRID.shape, np.float32), -10, -10, 10, 10, 3.0)
    h = _box(below, -7, -10, 13, 10, 3.0 + 2 * lh)  # two layers printed 3 mm off along +x
    sight = tr.Sight(C, TOP, GRID, 3.0 + 2 * lh)
    out = tr.layer_shift(sight, h, None, below, 3.0, np.array([3.0, 0.0]), 0.5 * lh)
    xy = _px(out)
    overlap = (xy[:, 0] > -5) & (xy[:, 0] < 8) & (np.abs(xy[:, 1]) < 8)
    assert overlap.sum() == 0  # a translated top looks like the planned one
    assert ((xy[:, 0] < -7) & (np.abs(xy[:, 1]) < 9)).sum() > 0.8 * 3 * 18 * TOP.px_per_mm**2  # left behind
    assert ((xy[:, 0] > 10) & (np.abs(xy[:, 1]) < 9)).sum() > 0.8 * 3 * 18 * TOP.px_per_mm**2  # overhang


def test_a_patch_failure_stays_truth_while_its_hole_is_open(part, camera, topview):
    """A hole cut on the onset layer is still truth on the next photo where the next layer left it open."""
    f = Failure("infill_defect", onset=4, size_mm=8.0, center_mm=(0.0, 0.0), seed=1, duration=3)
    sim = PrintSimulator(part, camera, topview, [f])
    first, second = sim.frame(4), sim.frame(5)
    assert first.truth is not None and second.truth is not None
    assert first.truth.sum() > 100
    # both layers miss the patch: the hole is deeper and at least as large
    assert (second.truth_area & first.truth_area).sum() >= 0.9 * first.truth_area.sum()
    after = sim.frame(4 + 3)  # the patch is over: no truth
    assert after.truth is None
