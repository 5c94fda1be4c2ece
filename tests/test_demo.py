"""The end-to-end demo, reduced: pauses within 2 layers of the onset and never before."""

from __future__ import annotations

import json

import pytest

from layerwatch.evaluate.demo import run_demo


@pytest.mark.slow
@pytest.mark.parametrize("failure,onset", [("spaghetti", 15), ("layer_shift", 5)])
def test_demo_pauses_soon_after_onset(tmp_path, failure, onset):
    res = run_demo(tmp_path / "out", layers=onset + 4, failure=failure, onset=onset, seed=1)
    assert res.paused_at is not None, res.anomaly
    assert onset <= res.paused_at <= onset + 2, (res.paused_at, res.anomaly)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["paused_at_layer"] == res.paused_at
    assert len(summary["layers"]) == res.paused_at + 1  # stopped at the pause
    assert (tmp_path / "out" / "stack.png").is_file()
    assert (tmp_path / "out" / "overlays" / f"layer_{res.paused_at:04d}.png").is_file()
    assert (tmp_path / "out" / "prepared.gcode").read_text().count("layerwatch snapshot") >= res.paused_at
    # the job is in the same history the monitor writes, with its report
    from layerwatch.storage import History

    with History(tmp_path / "out" / "history.db") as history:
        (job,) = history.jobs()
        assert job["outcome"] == "paused"
        assert len(history.layers(job["id"])) == res.paused_at + 1
        assert any(e["kind"] == "pause" for e in history.events(job["id"]))
        # the job keeps the settings it ran with, so the report draws the real pause threshold
        from layerwatch.pipeline.config import RECOMMENDED

        stored = history.job(job["id"])["config"]
        assert stored["policy"]["pause_ratio"] == RECOMMENDED["policy"]["pause_ratio"]
        assert job["id"] == res.job_id
        assert [r.decision for r in history.layers(job["id"])][-1] == "pause"  # the policy's, kept per layer
    assert (tmp_path / "out" / "refs" / f"layer_{res.paused_at:04d}.png").is_file()


@pytest.mark.slow
def test_demo_cli_reports_pause(tmp_path, capsys):
    from layerwatch.cli import main

    assert main(["demo", "--out", str(tmp_path / "o"), "--layers", "18", "--onset", "15"]) == 0
    text = capsys.readouterr().out
    assert "PAUSE at layer" in text
    # the HTML report of the job in the demo's history, with the pause threshold it ran with
    from layerwatch.pipeline.config import RECOMMENDED

    report = (tmp_path / "o" / "report" / "report.html").read_text()
    assert "<img" in report and f"{100 * RECOMMENDED['policy']['pause_ratio']:.1f} %" in report


def test_demo_cli_bad_failure_is_one_line(capsys):
    from layerwatch.cli import main

    assert main(["demo", "--failure", "nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "spaghetti" in err
