"""Recommended settings sit under the job file: the file's own keys win, overrides win over both."""

from layerwatch.pipeline.config import RECOMMENDED, JobConfig, recommended_config


def test_file_keys_win_over_recommended_and_overrides_win_over_the_file(tmp_path):
    job = tmp_path / "job.toml"
    job.write_text('[analysis]\nmetric = "cosine"\n[policy]\nconsecutive_layers = 3\n')
    cfg = recommended_config(job)
    assert cfg.analysis.metric == "cosine"  # the file's own choice
    assert cfg.analysis.threshold == RECOMMENDED["analysis"]["threshold"]  # not in the file
    assert cfg.analysis.presmooth_px == RECOMMENDED["analysis"]["presmooth_px"]
    assert cfg.policy.consecutive_layers == 3
    assert cfg.policy.pause_ratio == RECOMMENDED["policy"]["pause_ratio"]
    over = recommended_config(job, analysis={"metric": "pearson"})
    assert over.analysis.metric == "pearson"


def test_without_a_file_the_recommended_values_replace_the_paper_defaults():
    cfg = recommended_config()
    paper = JobConfig()
    assert paper.analysis.threshold == 0.7 and paper.analysis.presmooth_px == 0.0
    for key, value in RECOMMENDED["analysis"].items():
        assert getattr(cfg.analysis, key) == value
