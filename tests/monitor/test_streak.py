"""PlaceStreak: alarmed layers in a row, in the same place (rules 4, 4b and the per-kind thresholds)."""

from layerwatch.analysis.result import Region
from layerwatch.pipeline.streak import PlaceStreak, boxes_overlap


def _region(x: float, y: float, half: float = 2.0) -> Region:
    return Region(4 * half * half, (x - half, y - half, x + half, y + half), (x, y), 1, 0.5, 0.3, 0.0)


def test_boxes_overlap_touching_counts_and_apart_does_not():
    assert boxes_overlap((0, 0, 1, 1), (1, 1, 2, 2))
    assert not boxes_overlap((0, 0, 1, 1), (1.01, 0, 2, 1))


def test_same_place_counts_on_a_new_place_restarts_and_a_quiet_layer_ends():
    s = PlaceStreak()
    assert s.step(True, [_region(50, 50)]) == 1
    assert s.step(True, [_region(51, 50)]) == 2  # overlaps the previous layer's region
    assert s.step(True, [_region(150, 50)]) == 1  # elsewhere: a new streak
    assert s.step(False, [_region(150, 50)]) == 0 and s.regions == []
    assert s.step(True, [_region(150, 50)]) == 1


def test_an_alarm_without_regions_continues_and_reset_starts_afresh():
    s = PlaceStreak()
    s.step(True, [_region(50, 50)])
    assert s.step(True, []) == 2  # a% without regions is trusted
    assert s.step(True, [_region(150, 50)]) == 3  # after a layer without regions any place continues
    s.reset()
    assert (s.count, s.regions) == (0, [])
    assert s.step(True, [_region(150, 50)]) == 1
