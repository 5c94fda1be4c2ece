"""History database: round trip, upsert, migrations, corruption, crash safety."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.errors import StorageError
from layerwatch.storage.history import SCHEMA_VERSION, History


def _result(i: int, ratio: float = 0.01) -> LayerResult:
    return LayerResult(
        layer=i, z=0.3 * (i + 1), anomaly_ratio=ratio, metric="pearson", threshold=0.45,
        n_blocks=100, n_anomalous=int(ratio * 100),
        regions=[Region(area_mm2=4.0, bbox_mm=(1.0, 2.0, 3.0, 4.0), centroid_mm=(2.0, 3.0),
                        n_blocks=2, mean_similarity=0.2)],
        images={"overlay": f"layer_{i:04d}_overlay.png"}, timings_ms={"hog": 1.5},
    )


def test_round_trip(tmp_path):
    h = History(tmp_path / "h.db")
    assert h.schema_version == SCHEMA_VERSION
    job = h.start_job("mk4", gcode_path="part.gcode", gcode_hash="abc", part="cube", config={"a": 1})
    for i in range(5):
        h.add_layer(job, _result(i, 0.01 * i))
    h.add_event(job, "pause", "a% above 4 %", {"layer": 4})
    h.end_job(job, "paused")
    h.close()

    h = History(tmp_path / "h.db")
    got = h.layers(job)
    assert [r.layer for r in got] == list(range(5))
    assert got[3].to_dict() == _result(3, 0.03).to_dict()
    assert got[0].regions[0].bbox_mm == (1.0, 2.0, 3.0, 4.0)
    j = h.job(job)
    assert j["printer"] == "mk4" and j["outcome"] == "paused" and j["config"] == {"a": 1} and j["ended"] >= j["started"]
    (row,) = h.jobs()
    assert row["n_layers"] == 5 and row["max_anomaly_ratio"] == pytest.approx(0.04)
    (ev,) = h.events(job)
    assert ev["kind"] == "pause" and ev["data"] == {"layer": 4}
    assert h.job(999) is None and h.layers(999) == []


def test_upsert_by_job_and_layer(tmp_path):
    h = History(tmp_path / "h.db")
    job = h.start_job("p")
    h.add_layer(job, _result(2, 0.5))
    h.add_layer(job, _result(2, 0.1))
    (r,) = h.layers(job)
    assert r.anomaly_ratio == pytest.approx(0.1)
    assert h.layer_summary(job)[0]["anomaly_ratio"] == pytest.approx(0.1)


def test_nan_ratio_and_error_layers(tmp_path):
    h = History(":memory:")
    job = h.start_job("p")
    h.add_layer(job, LayerResult(layer=0, z=0.2, status="error", anomaly_ratio=float("nan"), message="no photo"))
    (r,) = h.layers(job)
    assert r.status == "error" and np.isnan(r.anomaly_ratio) and r.message == "no photo"
    assert h.layer_summary(job)[0]["anomaly_ratio"] is None


def test_unknown_job_write_raises(tmp_path):
    h = History(tmp_path / "h.db")
    with pytest.raises(StorageError, match="no job 7"):
        h.add_layer(7, _result(0))
    with pytest.raises(StorageError):
        h.end_job(7, "done")


def test_wal_and_pragmas(tmp_path):
    h = History(tmp_path / "h.db")
    assert h._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert h._db.execute("PRAGMA synchronous").fetchone()[0] == 1  # NORMAL


def test_newer_schema_refused(tmp_path):
    p = tmp_path / "h.db"
    History(p).close()
    with sqlite3.connect(p) as db:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    with pytest.raises(StorageError, match="upgrade layerwatch"):
        History(p)


def test_corrupt_file_is_one_line_error(tmp_path):
    p = tmp_path / "h.db"
    p.write_bytes(b"this is not sqlite at all" * 100)
    with pytest.raises(StorageError) as info:
        History(p)
    assert "\n" not in str(info.value)


def test_locked_database_is_storage_error(tmp_path):
    p = tmp_path / "h.db"
    h = History(p, timeout=0.05)
    job = h.start_job("p")
    other = sqlite3.connect(p, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        with pytest.raises(StorageError, match="failed"):
            h.add_layer(job, _result(0))
    finally:
        other.execute("ROLLBACK")
        other.close()
    h.add_layer(job, _result(0))
    assert len(h.layers(job)) == 1


WRITER = textwrap.dedent(
    """
    import sys
    from layerwatch.analysis.result import LayerResult
    from layerwatch.storage.history import History
    h = History(sys.argv[1])
    job = h.start_job("crash")
    i = 0
    while True:
        h.add_layer(job, LayerResult(layer=i, z=0.2 * i, anomaly_ratio=0.001 * i))
        print(i, flush=True)
        i += 1
    """
)


def test_sigkill_writer_loses_at_most_inflight_layer(tmp_path):
    p = tmp_path / "h.db"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(p)], stdout=subprocess.PIPE, text=True)
    acknowledged = -1
    for line in proc.stdout:
        acknowledged = int(line)
        if acknowledged >= 50:
            break
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    h = History(p)
    (job,) = h.jobs()
    got = h.layers(job["id"])
    idx = [r.layer for r in got]
    assert idx == list(range(len(idx)))
    # every acknowledged (committed) layer survives; at most the in-flight one beyond it
    assert len(idx) >= acknowledged + 1
    assert all(r.anomaly_ratio == pytest.approx(0.001 * r.layer) for r in got)
    h.add_layer(job["id"], LayerResult(layer=len(idx), z=1.0))


def test_huge_ids_match_nothing(tmp_path):
    h = History(tmp_path / "h.db")
    h.start_job("p")
    assert h.job(2**70) is None and h.layers(-(2**70)) == [] and h.events(1, after=2**80) == []
    with pytest.raises(StorageError, match="no job"):
        h.add_event(2**64, "x", "y")


def test_latest_layer(tmp_path):
    from layerwatch.analysis.result import LayerResult
    from layerwatch.storage.history import History

    with History(tmp_path / "h.db") as h:
        job = h.start_job("p")
        assert h.latest_layer(job) is None
        for i in (2, 0, 5, 1):
            h.add_layer(job, LayerResult(layer=i, z=0.2 * i, anomaly_ratio=i / 10))
        assert h.latest_layer(job).layer == 5 == h.layers(job)[-1].layer


def test_version_1_database_migrates_and_keeps_jobs(tmp_path):
    from layerwatch.storage.history import MIGRATIONS

    p = tmp_path / "v1.db"
    with sqlite3.connect(p) as db:  # a database written by the first release (schema 1 only)
        db.executescript(MIGRATIONS[0])
        db.execute("INSERT INTO printers(name, created) VALUES ('mk4', 0)")
        db.execute("INSERT INTO jobs(printer_id, started) VALUES (1, 0)")
        db.execute("PRAGMA user_version = 1")
    h = History(p)
    assert h.schema_version == SCHEMA_VERSION >= 2
    assert [j["printer"] for j in h.jobs()] == ["mk4"]
    assert h.setting("job_config") is None
    h.close()


def test_settings_round_trip_and_replace(tmp_path):
    from layerwatch.pipeline.config import JobConfig

    p = tmp_path / "h.db"
    h = History(p)
    h.set_setting("job_config", JobConfig.model_validate({"policy": {"pause_ratio": 0.2}}))
    h.set_setting("other", {"x": [1, 2]})
    h.set_setting("job_config", {"policy": {"pause_ratio": 0.3}})  # replaces, one row per name
    h.close()
    h = History(p)
    assert h.setting("job_config") == {"policy": {"pause_ratio": 0.3}} and h.setting("other") == {"x": [1, 2]}
    assert h._db.execute("SELECT COUNT(*) FROM settings").fetchone()[0] == 2
    h.close()
