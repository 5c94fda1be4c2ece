"""``layerwatch monitor --history DB`` applies the settings the dashboard saved in DB.

Precedence per key: --config file > dashboard (table ``settings``) > recommended > built-in defaults.
The runs use a real SQLite file, the real dashboard app to save the settings, and a short synthetic print
(6 layers) on the virtual printer with the simulated camera.
"""

import logging
import warnings

import pytest
from typer.testing import CliRunner

from layerwatch.cli import app
from layerwatch.cli.monitor import monitor_config
from layerwatch.errors import ConfigError
from layerwatch.pipeline.config import RECOMMENDED, JobConfig, recommended_config
from layerwatch.storage.history import History
from layerwatch.web.app import SETTINGS_KEY

# one layer above the pause ratio pauses, so the pause ratio alone decides whether the injected spaghetti pauses
TOPVIEW = "[topview]\nwidth_mm = 90\nheight_mm = 90\ncenter_mm = [110, 100]\n[policy]\nconsecutive_layers = 1\n"


def _save_in_dashboard(db, patch):
    """PATCH /api/settings through the real dashboard app, as the settings page does."""
    pytest.importorskip("fastapi")
    with warnings.catch_warnings():  # starlette's note about httpx vs httpx2, as in tests/web
        warnings.simplefilter("ignore")
        from fastapi.testclient import TestClient

    from layerwatch.web.app import create_app

    with History(db) as h:
        c = TestClient(create_app(h), base_url="http://127.0.0.1")  # loopback Host, with the page's CSRF token
        r = c.patch("/api/settings", json=patch, headers={"X-CSRF-Token": c.get("/api/session").json()["csrf"]})
        assert r.status_code == 200, r.text


@pytest.fixture(scope="module")
def gcode(tmp_path_factory):
    from layerwatch.simulate.parts import box_part, toolpath_gcode

    p = tmp_path_factory.mktemp("part") / "box.gcode"
    p.write_bytes(toolpath_gcode(box_part(size_mm=20.0, height_mm=1.8, layer_h=0.3, center=(110.0, 100.0), fin=False)))
    return p


def _monitor(tmp_path, gcode, db, *extra):
    cfg = tmp_path / "job.toml"
    if not cfg.exists():
        cfg.write_text(TOPVIEW)
    args = ["monitor", "--printer", "virtual", "--camera", "sim", "--gcode", str(gcode), "--history", str(db),
            "--failure", "spaghetti", "--onset", "2", "--wait-for-verdict", *extra]
    if "--config" not in extra:
        args += ["--config", str(cfg)]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    with History(db) as h:
        job = h.job(h.last_job_id())
    return r.output, JobConfig.model_validate(job["config"])


@pytest.mark.slow
def test_saved_dashboard_settings_reach_the_monitor_and_the_file_wins(tmp_path, gcode, caplog):
    db = tmp_path / "history.db"
    # baseline: nothing saved -> recommended settings, the injected spaghetti pauses
    out, used = _monitor(tmp_path, gcode, db)
    assert used.policy.pause_ratio == RECOMMENDED["policy"]["pause_ratio"]
    assert "1 pause(s)" in out, out

    # the dashboard saves a pause ratio far above the spaghetti's a%: the next monitor run uses it
    _save_in_dashboard(db, {"policy": {"pause_ratio": 0.31}})
    with caplog.at_level(logging.INFO, logger="layerwatch.monitor"):
        out, used = _monitor(tmp_path, gcode, db)
    assert used.policy.pause_ratio == 0.31 and used.policy.consecutive_layers == 1
    assert "0 pause(s)" in out, out
    # untouched keys keep the recommended values, not the dashboard's display of the built-in defaults
    assert used.analysis.metric == RECOMMENDED["analysis"]["metric"]
    assert used.analysis.threshold == RECOMMENDED["analysis"]["threshold"]
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("settings from:")]
    assert len(lines) == 1, lines
    assert "policy=file+dashboard+recommended" in lines[0] and "topview=file" in lines[0]
    assert "analysis=recommended" in lines[0] and "notify=default" in lines[0]

    # a --config file key wins over the dashboard's
    (tmp_path / "job.toml").write_text(TOPVIEW + "pause_ratio = 0.02\n")
    out, used = _monitor(tmp_path, gcode, db)
    assert used.policy.pause_ratio == 0.02
    assert "1 pause(s)" in out, out


def test_monitor_config_precedence_without_a_run(tmp_path):
    db = tmp_path / "h.db"
    toml = tmp_path / "job.toml"
    toml.write_text("[policy]\nconsecutive_layers = 4\n")
    with History(db) as h:
        cfg, src = monitor_config(toml, h)  # nothing saved yet
        assert cfg.policy.pause_ratio == RECOMMENDED["policy"]["pause_ratio"] and cfg.policy.consecutive_layers == 4
        assert src["policy"] == "file+recommended" and src["topview"] == "default"
        saved = recommended_config().model_dump(mode="json")  # what the dashboard stores: the full config it showed
        saved["policy"].update(pause_ratio=0.07, consecutive_layers=3)
        saved["analysis"]["grow_threshold"] = 0.3
        h.set_setting(SETTINGS_KEY, saved)
        cfg, src = monitor_config(toml, h)
    assert cfg.policy.pause_ratio == 0.07  # dashboard over recommended
    assert cfg.policy.consecutive_layers == 4  # file over dashboard
    assert cfg.analysis.grow_threshold == 0.3 and cfg.analysis.metric == RECOMMENDED["analysis"]["metric"]
    assert src["policy"] == "file+dashboard+recommended"  # recommended still gives skip_first_layers
    assert src["analysis"] == "dashboard+recommended"


def test_invalid_saved_settings_are_one_line_cli_error(tmp_path, gcode):
    db = tmp_path / "h.db"
    with History(db) as h:
        h.set_setting(SETTINGS_KEY, {"policy": {"pause_ratio": 7}})
        with pytest.raises(ConfigError, match=r"policy\.pause_ratio"):
            monitor_config(None, h)
    from layerwatch.cli import main

    rc = main(["monitor", "--printer", "virtual", "--camera", "sim", "--gcode", str(gcode), "--history", str(db)])
    assert rc == 2
