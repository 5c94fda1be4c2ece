"""The per-kind action policy, the resume grace period and ignored zones (issue 21)."""


import pytest

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.errors import ConfigError
from layerwatch.pipeline.config import JobConfig, resolve_config
from layerwatch.pipeline.policy import KindActions, PausePolicy, PolicySettings
from layerwatch.web.settings import SettingsRejected, validate_settings

PRINTED = 1000.0


def _region(area, x=100.0, y=100.0, kind=""):
    h = max(area, 1.0) ** 0.5 / 2
    return Region(area, (x - h, y - h, x + h, y + h), (x, y), max(int(area // 4), 1), 0.5, 0.3, 0.0, kind)


def _res(layer, regions=(), ratio=None):
    regions = list(regions)
    area = sum(r.area_mm2 for r in regions) if ratio is None else ratio * PRINTED
    return LayerResult(layer=layer, z=0.3 * (layer + 1), status="ok", anomaly_ratio=area / PRINTED,
                       printed_area_mm2=PRINTED, anomalous_area_mm2=area, regions=regions)


def _kinds(**kw):
    return KindActions.model_validate({k: v for k, v in kw.items()})


def _run(policy, layers):
    out = None
    for i, regs in enumerate(layers, start=2):
        out = policy.update(_res(i, regs))
        if out.stops:
            return out
    return out


def test_untyped_region_keeps_todays_pause_and_follows_the_rule_action():
    d = _run(PausePolicy(PolicySettings()), [[_region(150)]] * 2)
    assert d.action == "pause" and d.kind == "unknown"
    d = _run(PausePolicy(PolicySettings(action="cancel")), [[_region(150)]] * 2)
    assert d.action == "cancel" and d.kind == "unknown"


def test_detachment_defaults_to_cancel_object_with_its_regions():
    d = _run(PausePolicy(PolicySettings()), [[_region(150, kind="detachment")]] * 2)
    assert d.action == "cancel_object" and d.kind == "detachment" and d.stops
    assert d.regions and d.regions[0].kind == "detachment"


def test_kind_action_replaces_the_rules_action():
    s = PolicySettings(kinds=_kinds(infill_defect={"action": "notify"},
                                    spaghetti={"action": "host_command", "command": "COOL_DOWN"}))
    p = PausePolicy(s)
    d = _run(p, [[_region(150, kind="infill_defect")]] * 4)
    assert d.action == "notify" and not p.halted
    d = _run(PausePolicy(s), [[_region(150, kind="spaghetti")]] * 2)
    assert d.action == "host_command" and d.command == "COOL_DOWN" and d.stops


def test_pausing_switched_off_turns_every_kind_into_a_notification():
    p = PausePolicy(PolicySettings(action="notify", strong_action="notify"))
    for i in range(2, 8):
        assert p.update(_res(i, [_region(150, kind="detachment")])).action in ("none", "notify")
    assert not p.halted


def test_act_threshold_per_kind_more_and_less_sensitive():
    # spaghetti stops on 8 mm^2, far below the general rules (min_area 5 mm^2 but a% 10 %)
    s = PolicySettings(pause_ratio=0.1, kinds=_kinds(spaghetti={"act_mm2": 8}))
    d = _run(PausePolicy(s), [[_region(9, kind="spaghetti")]] * 3)
    assert d.stops and "spaghetti" in d.reason and d.layer == 3
    assert not _run(PausePolicy(PolicySettings(pause_ratio=0.1)), [[_region(9, kind="spaghetti")]] * 3).stops
    # thin walls only at 500 mm^2: the general rule's 150 mm^2 notifies
    s = PolicySettings(kinds=_kinds(thin_wall={"act_mm2": 500}))
    d = _run(PausePolicy(s), [[_region(150, kind="thin_wall")]] * 4)
    assert d.action == "notify" and "own" in d.reason
    d = _run(PausePolicy(s), [[_region(600, kind="thin_wall")]] * 2)
    assert d.stops


def test_warn_threshold_per_kind_notifies():
    s = PolicySettings(pause_ratio=0.5, kinds=_kinds(foreign_body={"warn_mm2": 20}))
    p = PausePolicy(s)
    assert p.update(_res(2, [_region(10, kind="foreign_body")])).action == "none"
    d = p.update(_res(3, [_region(30, kind="foreign_body", x=20)]))
    assert d.action == "notify" and "foreign_body" in d.reason and not d.stops


def test_resume_grace_no_repause_on_unchanged_regions_then_rules_again():
    s = PolicySettings(resume_grace_layers=3, pause_ratio=0.1)
    p = PausePolicy(s)
    assert _run(p, [[_region(150)]] * 2).stops
    p.acknowledge()
    # diffuse anomaly right after the resume (no new region): quiet for 3 layers, then the a% rule again
    acts = [p.update(_res(i, [_region(150)], ratio=0.4)).action for i in range(4, 9)]
    assert acts[:3] == ["none"] * 3 and "pause" in acts[3:], acts
    # without a grace period the same stream pauses at once
    q = PausePolicy(PolicySettings(resume_grace_layers=0, pause_ratio=0.1))
    _run(q, [[_region(150)]] * 2)
    q.acknowledge()
    acts = [q.update(_res(i, [_region(150)], ratio=0.4)).action for i in range(4, 6)]
    assert acts[-1] == "pause", acts
    # growth within the grace period pauses
    r = PausePolicy(s)
    _run(r, [[_region(150)]] * 2)
    r.acknowledge()
    assert r.update(_res(4, [_region(400)])).stops


def test_ignored_zone_raises_no_alarm_later():
    p = PausePolicy(PolicySettings(pause_ratio=0.05))
    d = _run(p, [[_region(150, kind="detachment")]] * 2)
    assert d.action == "cancel_object"
    p.ignore_zone((80, 80, 120, 120), "B")
    assert not p.halted
    for i in range(5, 30):
        assert p.update(_res(i, [_region(150 + 10 * i, kind="spaghetti")])).action == "none"
    # a failure on another object still stops
    assert _run(p, [[_region(150, x=30)]] * 2).stops


def test_a_cancelled_objects_remains_reaching_out_of_its_zone_are_ignored_unless_they_touch_a_printed_object():
    """A detached part's change beside the print reaches past its box (plus margin): with the boxes of the objects
    still printed, a region overlapping the zone and none of them is the cancelled object's; one that touches a
    printed object still counts; the layers-in-a-row counts start afresh after the cancel."""
    p = PausePolicy(PolicySettings(pause_ratio=0.05))
    assert _run(p, [[_region(150, kind="detachment")]] * 2).action == "cancel_object"
    p.ignore_zone((80, 80, 120, 120), "B", others=[(80, 125, 120, 160)])
    reaching = _region(64, x=124.0, y=100.0)  # centred 4 mm beyond the zone, box 120..128 overlaps it
    for i in range(5, 12):
        assert p.update(_res(i, [reaching])).action == "none"
    touching = _region(64, x=120.0, y=123.0)  # overlaps the zone and the printed object's box
    assert _run(p, [[touching]] * 3).stops
    q = PausePolicy(PolicySettings(pause_ratio=0.05))  # without the others' boxes: centred in the zone only
    assert _run(q, [[_region(150, kind="detachment")]] * 2).action == "cancel_object"
    q.ignore_zone((80, 80, 120, 120), "B")
    assert _run(q, [[reaching]] * 3).stops


@pytest.mark.parametrize(("where", "counts"), [
    ("beside", False),  # 2 mm past the zone, 47 mm from the printed object: the remains of a part that moved
    ("far", True),  # 18 mm past the zone (beyond REMAINS_REACH_MM): something else on the bed
    ("nearer_printed", True),  # 0.6 mm past the zone but 0.4 mm from the printed object: it can meet the nozzle
    ("centred_touching", True),  # centred in the zone, its box reaches the printed object's
])
def test_a_cancelled_objects_remains_beside_its_zone_are_its_own_unless_nearer_a_printed_object(where, counts):
    """A detached part's change reaches a few mm past its moved outline, beyond the zone (box plus margin): a region
    that touches no printed object and lies nearer the cancelled zone than any of them, within REMAINS_REACH_MM,
    is the cancelled object's (the real-Klippy plate test's 'changed beside the print' after B's cancel)."""
    from layerwatch.pipeline.policy import REMAINS_REACH_MM

    region = {"beside": _region(16, x=100.0, y=76.0), "far": _region(16, x=100.0, y=60.0),
              "nearer_printed": _region(16, x=100.0, y=122.6),
              "centred_touching": _region(144, x=100.0, y=119.5)}[where]
    p = PausePolicy(PolicySettings(pause_ratio=0.01, min_area_mm2=1.0))
    assert _run(p, [[_region(150, kind="detachment")]] * 2).action == "cancel_object"
    p.ignore_zone((80, 80, 120, 120), "B", others=[(80, 125, 120, 160)])
    assert REMAINS_REACH_MM < 18
    assert bool(_run(p, [[region]] * 3).stops) is counts
    q = PausePolicy(PolicySettings(pause_ratio=0.01, min_area_mm2=1.0))  # the same region before any cancel: counts
    assert _run(q, [[region]] * 3).stops


def test_config_tables_per_kind(tmp_path):
    f = tmp_path / "job.toml"
    f.write_text('[policy.kinds.detachment]\nact_mm2 = 40\n[policy.kinds.spaghetti]\naction = "cancel"\n')
    cfg = resolve_config(f, dashboard={"policy": {"kinds": {"detachment": {"warn_mm2": 5}}}}).config
    k = cfg.policy.kinds
    assert (k.detachment.action, k.detachment.act_mm2, k.detachment.warn_mm2) == ("cancel_object", 40, 5)
    assert k.spaghetti.action == "cancel" and k.of("") is k.unknown and k.unknown.action == "rule"
    for bad in ('[policy.kinds.spaghetti]\naction = "explode"\n', '[policy.kinds.spaghetti]\nact_mm2 = inf\n',
                '[policy.kinds.spaghetti]\naction = "host_command"\n', '[policy.kinds.martian]\naction = "pause"\n',
                '[policy.kinds.spaghetti]\naction = "host_command"\ncommand = "M104 S0\\nM84"\n'):
        f.write_text(bad)
        with pytest.raises(ConfigError, match="policy.kinds"):
            resolve_config(f)


def test_dashboard_refuses_to_silence_a_failure_kind():
    current = JobConfig()
    data = current.model_dump(mode="json")
    data["policy"]["kinds"]["spaghetti"]["action"] = "notify"
    with pytest.raises(SettingsRejected, match="policy.kinds.spaghetti.action"):
        validate_settings(data, current)
    data["policy"]["kinds"]["spaghetti"] = {"action": "pause", "act_mm2": 3000}
    with pytest.raises(SettingsRejected, match="allowed: 0 to 2500"):
        validate_settings(data, current)
    data["policy"]["kinds"]["spaghetti"] = {"action": "cancel_object", "act_mm2": 40}
    assert validate_settings(data, current).policy.kinds.spaghetti.act_mm2 == 40
