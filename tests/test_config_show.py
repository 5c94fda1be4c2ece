"""The settings resolver and ``layerwatch config show``: every value with its source."""

from __future__ import annotations

import json

import pytest

from layerwatch.cli import main
from layerwatch.errors import ConfigError
from layerwatch.pipeline.config import RECOMMENDED, resolve_config


def _show(capsys, *args) -> dict:
    assert main(["config", "show", "--json", *args]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.fixture
def job_file(tmp_path):
    path = tmp_path / "job.toml"
    path.write_text("[analysis]\nthreshold = 0.35\n[policy]\npause_ratio = 0.05\n")
    return path


def test_default_value(capsys, job_file):
    rows = _show(capsys, "-c", str(job_file))
    assert rows["analysis.cell_px"] == {"value": 8, "source": "default"}
    assert rows["policy.min_area_mm2"] == {"value": 5.0, "source": "default"}


def test_recommended_value_and_paper_settings(capsys, job_file):
    rows = _show(capsys, "-c", str(job_file))
    assert rows["analysis.metric"] == {"value": RECOMMENDED["analysis"]["metric"], "source": "recommended"}
    paper = _show(capsys, "-c", str(job_file), "--paper-settings")
    assert paper["analysis.metric"] == {"value": "cosine", "source": "default"}


def test_file_value_wins_over_recommended(capsys, job_file):
    rows = _show(capsys, "-c", str(job_file))
    assert rows["analysis.threshold"] == {"value": 0.35, "source": "file"}
    assert rows["policy.pause_ratio"] == {"value": 0.05, "source": "file"}


def test_flag_value_wins_over_file(capsys, job_file):
    rows = _show(capsys, "-c", str(job_file), "--set", "analysis.threshold=0.4", "--set", "analysis.metric=pearson")
    assert rows["analysis.threshold"] == {"value": 0.4, "source": "flag"}
    assert rows["analysis.metric"] == {"value": "pearson", "source": "flag"}


def test_gcode_derived_value_without_a_job_file(capsys, tmp_path):
    from layerwatch.examples import PART_GCODE

    rows = _show(capsys, "--gcode", str(PART_GCODE))
    assert rows["topview.center_mm"]["source"] == "gcode"
    assert rows["topview.px_per_mm"]["source"] == "default"


def test_every_key_has_a_source_and_the_table_prints(capsys, job_file):
    assert main(["config", "show", "-c", str(job_file)]) == 0
    text = capsys.readouterr().out
    assert f"job file: {job_file}" in text
    line = next(ln for ln in text.splitlines() if ln.startswith("analysis.threshold "))
    assert line.split()[1:] == ["0.35", "file"]
    resolved = resolve_config(job_file)
    assert set(resolved.sources.values()) <= {"default", "recommended", "file"}
    for section, model in resolved.config:
        assert all(f"{section}.{key}" in resolved.sources for key in type(model).model_fields)


def test_dashboard_layer_sits_between_recommended_and_file(job_file):
    r = resolve_config(job_file, dashboard={"policy": {"pause_ratio": 0.2, "consecutive_layers": 3}})
    assert r.config.policy.pause_ratio == 0.05 and r.sources["policy.pause_ratio"] == "file"
    assert r.config.policy.consecutive_layers == 3 and r.sources["policy.consecutive_layers"] == "dashboard"
    assert r.section_sources()["policy"] == "file+dashboard+recommended"


def test_bad_values_are_one_line_naming_their_origin(capsys, job_file, tmp_path):
    with pytest.raises(ConfigError, match="command-line setting analysis.threshold"):
        resolve_config(job_file, flags={"analysis": {"threshold": 2.0}})
    bad = tmp_path / "bad.toml"
    bad.write_text("[analysis]\nthreshold = -1\n")
    with pytest.raises(ConfigError, match=f"{bad}: invalid setting analysis.threshold"):
        resolve_config(bad)
    assert main(["config", "show", "--set", "threshold=0.3"]) == 2
    assert capsys.readouterr().err.strip().startswith("error:")


def test_paper_settings_mean_the_same_for_the_monitor_and_analyze(job_file):
    from layerwatch.cli.monitor import monitor_config
    from layerwatch.cli.pipeline import job_settings

    cfg, sources = monitor_config(job_file, paper=True)
    offline = job_settings(job_file, None, paper=True)
    assert cfg == offline.config and cfg.analysis.metric == "cosine" and cfg.policy.pause_ratio == 0.05
    assert sources["analysis"] == "file" and sources["markers"] == "default"
    assert monitor_config(job_file)[0] == job_settings(job_file, None).config  # and without the flag

