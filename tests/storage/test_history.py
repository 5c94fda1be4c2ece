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
    # the killed writer's job is no longer "running": interrupted, with its last stored layer
    assert h.interrupted == [job["id"]]
    j = h.job(job["id"])
    assert j["outcome"] == "interrupted" and j["last_layer"] == idx[-1] and j["ended"] >= j["started"]
    ev = h.events(job["id"])[-1]
    assert ev["kind"] == "interrupted" and ev["data"] == {"last_layer": idx[-1]}
    assert f"last stored layer is {idx[-1]}" in ev["message"]
    h.add_layer(job["id"], LayerResult(layer=len(idx), z=1.0))
    h.close()
    assert History(p).interrupted == []  # marked once


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


def test_running_writer_is_not_marked_interrupted(tmp_path):
    """A job written by a live process (this one, or a monitor beside the dashboard) stays running."""
    p = tmp_path / "h.db"
    with History(p) as writer:
        job = writer.start_job("live")
        writer.add_layer(job, _result(0))
        with History(p) as dashboard:  # a second connection opened while the writer runs
            assert dashboard.interrupted == [] and dashboard.job(job)["outcome"] is None


def test_recycled_pid_counts_as_gone(tmp_path):
    from layerwatch.storage.owner import is_gone, this_process

    me = this_process()
    assert not is_gone(me) and not is_gone(None) and not is_gone({**me, "host": "elsewhere"})
    if me["start"] is not None:
        assert is_gone({**me, "start": me["start"] + 1})  # same pid, another process start time


PERMS = textwrap.dedent(
    """
    import os, stat, sys
    os.umask(int(sys.argv[2], 8))
    from layerwatch.storage.history import History
    from layerwatch.web.token import load_or_create_token
    h = History(sys.argv[1] + "/sub/history.db")
    h.add_event(h.start_job("p"), "x", "y")  # writes: the WAL and SHM exist now
    load_or_create_token(sys.argv[1] + "/sub/history.token")
    for name in ("history.db", "history.db-wal", "history.db-shm", "history.token", ""):
        print(name or "folder", oct(stat.S_IMODE(os.stat(sys.argv[1] + "/sub/" + name).st_mode)))
    """
)


@pytest.mark.parametrize("umask", ["000", "022", "277"])
def test_database_wal_shm_and_token_are_0600_whatever_the_umask(tmp_path, umask):
    out = subprocess.run([sys.executable, "-c", PERMS, str(tmp_path), umask], capture_output=True, text=True, check=True)
    modes = dict(line.split() for line in out.stdout.splitlines())
    assert modes == {"history.db": "0o600", "history.db-wal": "0o600", "history.db-shm": "0o600",
                     "history.token": "0o600", "folder": oct(0o700 & ~int(umask, 8))}, modes


def test_existing_world_readable_database_is_tightened(tmp_path):
    p = tmp_path / "h.db"
    History(p).close()
    os.chmod(p, 0o644)
    History(p).close()
    assert (p.stat().st_mode & 0o777) == 0o600


def test_audit_log_round_trip(tmp_path):
    p = tmp_path / "h.db"
    with History(p) as h:
        a = h.add_audit("pause", "127.0.0.1", "local (no token)", "printer mk4", {"job_id": 3})
        b = h.add_audit("settings", "10.0.0.2", "token session 1a2b", None, {"policy.pause_ratio": 0.2})
    with History(p) as h:
        rows = h.audit()
        assert [r["id"] for r in rows] == [b, a]  # newest first
        assert rows[1] | {"time": 0} == {"id": a, "time": 0, "action": "pause", "target": "printer mk4",
                                         "client": "127.0.0.1", "actor": "local (no token)", "detail": {"job_id": 3}}
        assert [r["id"] for r in h.audit(after=a)] == [b] and len(h.audit(limit=1)) == 1


def test_artifacts_are_the_layers_image_paths(tmp_path):
    from layerwatch.storage.history import MIGRATIONS

    p = tmp_path / "v2.db"
    with sqlite3.connect(p) as db:  # schema 2 with a stored layer: the migration backfills its images
        db.executescript(MIGRATIONS[0] + MIGRATIONS[1])
        db.execute("INSERT INTO printers(name, created) VALUES ('mk4', 0)")
        db.execute("INSERT INTO jobs(printer_id, started) VALUES (1, 0)")
        db.execute("INSERT INTO layers VALUES (1, 0, 0.2, 0.0, 'ok', 'jaccard', 0.2, ?, 0)", (_result(0).to_json(),))
        db.execute("PRAGMA user_version = 2")
    with History(p) as h:
        assert h.is_artifact("layer_0000_overlay.png")
        h.add_layer(1, _result(1))
        assert h.is_artifact("layer_0001_overlay.png")
        assert not h.is_artifact("history.db") and not h.is_artifact("../layer_0001_overlay.png")
        assert h.job(1)["outcome"] is None  # no owner recorded before version 3: never judged
