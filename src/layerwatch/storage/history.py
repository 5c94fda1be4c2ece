"""Print history in SQLite: printers, jobs, per-layer results, events and the audit log.

One database file holds every job, the settings edited in the dashboard
(table ``settings``) and the dashboard's audit log (table ``audit``: who
paused, resumed, cancelled, acknowledged or changed settings, from which
client, when). The file, its WAL and shared-memory files are created with
mode 0600 whatever the umask (they hold printer keys and notification URLs).
Each job records the process writing it; a job whose process died without
ending it is marked ``interrupted`` (with its last layer) the next time the
database is opened. It is opened in WAL mode with
``synchronous=NORMAL`` so that a crash (even SIGKILL of the writer) loses at
most the layer being written; each :meth:`History.add_layer` is one
transaction. The schema version lives in ``PRAGMA user_version`` and the
:data:`MIGRATIONS` list is applied in order on open.
"""

from __future__ import annotations

import json
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from layerwatch.analysis.result import LayerResult
from layerwatch.errors import StorageError
from layerwatch.storage.owner import is_gone, this_process

__all__ = ["History", "MIGRATIONS", "SCHEMA_VERSION"]

log = logging.getLogger("layerwatch.storage")

MIGRATIONS: list[str] = [
    # version 1
    """
    CREATE TABLE printers (
        id INTEGER PRIMARY KEY,
        name TEXT NOT NULL UNIQUE,
        created REAL NOT NULL
    );
    CREATE TABLE jobs (
        id INTEGER PRIMARY KEY,
        printer_id INTEGER NOT NULL REFERENCES printers(id),
        gcode_path TEXT,
        gcode_hash TEXT,
        part TEXT,
        config TEXT,
        started REAL NOT NULL,
        ended REAL,
        outcome TEXT
    );
    CREATE TABLE layers (
        job_id INTEGER NOT NULL REFERENCES jobs(id),
        layer INTEGER NOT NULL,
        z REAL NOT NULL,
        anomaly_ratio REAL,
        status TEXT NOT NULL,
        metric TEXT NOT NULL,
        threshold REAL NOT NULL,
        result TEXT NOT NULL,
        created REAL NOT NULL,
        PRIMARY KEY (job_id, layer)
    );
    CREATE TABLE events (
        id INTEGER PRIMARY KEY,
        job_id INTEGER NOT NULL REFERENCES jobs(id),
        time REAL NOT NULL,
        kind TEXT NOT NULL,
        message TEXT NOT NULL,
        data TEXT
    );
    CREATE INDEX events_job ON events(job_id, id);
    """,
    # version 2: settings edited in the dashboard (JSON per name), kept across restarts
    """
    CREATE TABLE settings (
        name TEXT PRIMARY KEY,
        value TEXT NOT NULL,
        updated REAL NOT NULL
    );
    """,
    # version 3: the writing process of each job (to find interrupted jobs), the dashboard's audit
    # log, and the artifacts (image files) the layers refer to: the only files the dashboard serves
    """
    ALTER TABLE jobs ADD COLUMN owner TEXT;
    CREATE TABLE audit (
        id INTEGER PRIMARY KEY,
        time REAL NOT NULL,
        action TEXT NOT NULL,
        target TEXT,
        client TEXT NOT NULL,
        actor TEXT NOT NULL,
        detail TEXT
    );
    CREATE TABLE artifacts (
        path TEXT PRIMARY KEY,
        job_id INTEGER NOT NULL REFERENCES jobs(id)
    );
    INSERT OR IGNORE INTO artifacts(path, job_id)
        SELECT je.value, l.job_id FROM layers l, json_each(l.result, '$.images') je
        WHERE je.type = 'text';
    """,
]
SCHEMA_VERSION = len(MIGRATIONS)

_JOB_COLS = "j.id, p.name, j.gcode_path, j.gcode_hash, j.part, j.config, j.started, j.ended, j.outcome"
_JOB_KEYS = ("id", "printer", "gcode_path", "gcode_hash", "part", "config", "started", "ended", "outcome")
_AUDIT_KEYS = ("id", "time", "action", "target", "client", "actor", "detail")
PRIVATE = 0o600  # mode of the database, its WAL/SHM files and the dashboard token


def _make_private(path: Path) -> None:
    """Create ``path`` (and its folder, 0700) with mode 0600 whatever the umask; tighten our wider files.

    SQLite gives the ``-wal``, ``-shm`` and ``-journal`` files it creates the
    database file's mode, so making the database 0600 before SQLite opens it
    makes them 0600 as well; existing ones (from an older layerwatch) that
    others could read are set to 0600 too.
    """
    if not path.parent.exists():
        path.parent.mkdir(parents=True, mode=0o700)
    if not path.exists():
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, PRIVATE)
        except FileExistsError:  # another process created it just now
            pass
        else:
            os.fchmod(fd, PRIVATE)
            os.close(fd)
    for name in ("", "-wal", "-shm", "-journal"):
        side = path.with_name(path.name + name)
        try:
            st = side.stat()
        except FileNotFoundError:
            continue
        if st.st_uid == os.getuid() and st.st_mode & 0o077:
            os.chmod(side, PRIVATE)


def _int(value: Any) -> int:
    """``int(value)`` clamped to SQLite's 64-bit range (an id beyond it simply matches nothing)."""
    return max(-(2**63), min(2**63 - 1, int(value)))


def _inserted_id(cur: sqlite3.Cursor) -> int:
    """The id of the row an ``INSERT`` just added (sqlite3 sets ``lastrowid`` after each one)."""
    rowid = cur.lastrowid
    assert rowid is not None
    return int(rowid)


def _config_json(config: Any) -> str | None:
    if config is None:
        return None
    if hasattr(config, "model_dump"):
        return json.dumps(config.model_dump(mode="json"))
    return json.dumps(config)


class History:
    """The history database.

    Parameters
    ----------
    path : str or Path
        SQLite file; created (with parent folders) if missing. ``":memory:"``
        gives a private in-memory database.
    timeout : float
        Seconds to wait for a lock held by another writer.

    Raises
    ------
    StorageError
        The file is not a database, is locked, or has a newer schema.
    """

    def __init__(self, path: str | Path, timeout: float = 5.0) -> None:
        self.path = Path(path) if str(path) != ":memory:" else None
        self._lock = threading.RLock()
        where = str(path)
        try:
            if self.path is not None:
                _make_private(self.path)
            self._db = sqlite3.connect(where, timeout=timeout, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute("PRAGMA foreign_keys=ON")
            self._migrate()
        except sqlite3.Error as exc:
            raise StorageError(
                f"cannot open history database {where}: {exc}; "
                "close other layerwatch processes or move the file aside and start a new one."
            ) from None
        except OSError as exc:
            raise StorageError(f"cannot create history database {where}: {exc.strerror}; "
                               "check the folder exists and is writable.") from None
        try:
            self.interrupted = self.mark_interrupted()
        except StorageError as exc:  # e.g. a read-only copy: reading still works
            log.warning("could not mark interrupted jobs: %s", exc)
            self.interrupted = []

    # -- plumbing -----------------------------------------------------------------
    def _migrate(self) -> None:
        version = self._db.execute("PRAGMA user_version").fetchone()[0]
        if version > SCHEMA_VERSION:
            raise StorageError(
                f"history database {self.path} has schema version {version}, newer than this "
                f"layerwatch ({SCHEMA_VERSION}); upgrade layerwatch."
            )
        for i in range(version, SCHEMA_VERSION):
            self._db.execute("BEGIN IMMEDIATE")
            try:
                for stmt in MIGRATIONS[i].split(";"):
                    if stmt.strip():
                        self._db.execute(stmt)
                self._db.execute(f"PRAGMA user_version = {i + 1}")
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise

    def _run(self, fn: Callable[[sqlite3.Connection], Any], write: bool = False) -> Any:
        with self._lock:
            try:
                if not write:
                    return fn(self._db)
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    out = fn(self._db)
                    self._db.execute("COMMIT")
                    return out
                except BaseException:
                    self._db.execute("ROLLBACK")
                    raise
            except sqlite3.Error as exc:
                raise StorageError(
                    f"history database {self.path or ':memory:'} failed: {exc}; "
                    "check the disk and that no other process holds the file."
                ) from None

    def close(self) -> None:
        """Close the connection."""
        with self._lock:
            self._db.close()

    def __enter__(self) -> History:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def schema_version(self) -> int:
        return self._run(lambda db: db.execute("PRAGMA user_version").fetchone()[0])

    # -- writing ------------------------------------------------------------------
    def start_job(
        self,
        printer: str,
        gcode_path: str | Path | None = None,
        gcode_hash: str | None = None,
        part: str | None = None,
        config: Any = None,
    ) -> int:
        """Record a new job and return its id.

        ``config`` may be a pydantic model (e.g. ``JobConfig``) or a JSON-able dict.
        """
        cfg = _config_json(config)

        def fn(db: sqlite3.Connection) -> int:
            now = time.time()
            db.execute("INSERT OR IGNORE INTO printers(name, created) VALUES (?, ?)", (printer, now))
            pid = db.execute("SELECT id FROM printers WHERE name = ?", (printer,)).fetchone()[0]
            cur = db.execute(
                "INSERT INTO jobs(printer_id, gcode_path, gcode_hash, part, config, started, owner) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (pid, None if gcode_path is None else str(gcode_path), gcode_hash, part, cfg, now,
                 json.dumps(this_process())),
            )
            return _inserted_id(cur)

        return self._run(fn, write=True)

    def _check_job(self, db: sqlite3.Connection, job_id: int) -> None:
        if db.execute("SELECT 1 FROM jobs WHERE id = ?", (_int(job_id),)).fetchone() is None:
            raise StorageError(f"no job {job_id} in the history; list jobs with `layerwatch history`.")

    def add_layer(self, job_id: int, result: LayerResult) -> None:
        """Store (or replace) one layer's result; one transaction per call."""
        text = result.to_json()
        ratio: float | None = result.anomaly_ratio
        ratio = None if ratio is None or ratio != ratio else float(ratio)

        def fn(db: sqlite3.Connection) -> None:
            self._check_job(db, job_id)
            db.execute(
                "INSERT INTO layers(job_id, layer, z, anomaly_ratio, status, metric, threshold, result, created) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT(job_id, layer) DO UPDATE SET "
                "z=excluded.z, anomaly_ratio=excluded.anomaly_ratio, status=excluded.status, "
                "metric=excluded.metric, threshold=excluded.threshold, result=excluded.result, "
                "created=excluded.created",
                (_int(job_id), _int(result.layer), float(result.z), ratio, result.status,
                 result.metric, float(result.threshold), text, time.time()),
            )
            db.executemany("INSERT OR IGNORE INTO artifacts(path, job_id) VALUES (?, ?)",
                           [(str(p), _int(job_id)) for p in result.images.values() if isinstance(p, str)])

        self._run(fn, write=True)

    def add_event(self, job_id: int, kind: str, message: str, data: Any = None) -> int:
        """Append an event (``kind`` e.g. ``"pause"``, ``"notify"``, ``"error"``); returns its id."""
        payload = None if data is None else json.dumps(data, default=str)

        def fn(db: sqlite3.Connection) -> int:
            self._check_job(db, job_id)
            cur = db.execute(
                "INSERT INTO events(job_id, time, kind, message, data) VALUES (?, ?, ?, ?, ?)",
                (_int(job_id), time.time(), str(kind), str(message), payload),
            )
            return _inserted_id(cur)

        return self._run(fn, write=True)

    def end_job(self, job_id: int, outcome: str) -> None:
        """Mark a job finished with ``outcome`` (``"done"``, ``"paused"``, ``"cancelled"``, ``"failed"``).

        ``"interrupted"`` is set by :meth:`mark_interrupted` for jobs nobody ended.
        """

        def fn(db: sqlite3.Connection) -> None:
            self._check_job(db, job_id)
            db.execute("UPDATE jobs SET ended = ?, outcome = ? WHERE id = ?", (time.time(), outcome, _int(job_id)))

        self._run(fn, write=True)

    def mark_interrupted(self) -> list[int]:
        """Mark jobs whose writing process is gone (killed, crashed) as ``interrupted``; return their ids.

        Each gets ``ended`` = the time of its last stored layer (or its start)
        and an ``interrupted`` event naming that layer. Jobs written by a
        running process, by another host, or before owners were recorded are
        left alone. Called on open.
        """

        def fn(db: sqlite3.Connection) -> list[int]:
            rows = db.execute("SELECT id, owner, started FROM jobs WHERE outcome IS NULL AND owner IS NOT NULL").fetchall()
            done = []
            for job_id, owner, started in rows:
                if not is_gone(json.loads(owner)):
                    continue
                last, at = db.execute("SELECT MAX(layer), MAX(created) FROM layers WHERE job_id = ?", (job_id,)).fetchone()
                db.execute("UPDATE jobs SET ended = ?, outcome = 'interrupted' WHERE id = ?", (at or started, job_id))
                said = "no layer was stored" if last is None else f"its last stored layer is {last}"
                db.execute(
                    "INSERT INTO events(job_id, time, kind, message, data) VALUES (?, ?, 'interrupted', ?, ?)",
                    (job_id, time.time(), f"the monitoring process stopped without ending the job; {said}",
                     json.dumps({"last_layer": last})),
                )
                done.append(int(job_id))
            return done

        return self._run(fn, write=True)

    def add_audit(self, action: str, client: str, actor: str, target: str | None = None, detail: Any = None) -> int:
        """Append a dashboard action to the audit log; returns its id.

        Parameters
        ----------
        action : str
            ``"pause"``, ``"resume"``, ``"cancel"``, ``"acknowledge"``, ``"settings"``, ``"pausing off"``, ...
        client : str
            Network address of the requesting client.
        actor : str
            Who: ``"token session 1a2b3c4d"``, ``"local (no token)"``.
        target : str, optional
            What it acted on (``"printer virtual"``, ``"job 3"``).
        detail : JSON-able, optional
            E.g. the changed settings (redacted by the caller).
        """
        payload = None if detail is None else json.dumps(detail, default=str)

        def fn(db: sqlite3.Connection) -> int:
            cur = db.execute(
                "INSERT INTO audit(time, action, target, client, actor, detail) VALUES (?, ?, ?, ?, ?, ?)",
                (time.time(), str(action), target, str(client), str(actor), payload),
            )
            return _inserted_id(cur)

        return self._run(fn, write=True)

    def audit(self, after: int = 0, limit: int = 200) -> list[dict[str, Any]]:
        """Audit entries with id greater than ``after``, newest first, at most ``limit``."""
        rows = self._run(lambda db: db.execute(
            "SELECT id, time, action, target, client, actor, detail FROM audit WHERE id > ? ORDER BY id DESC LIMIT ?",
            (_int(after), max(0, _int(limit))),
        ).fetchall())
        out = [dict(zip(_AUDIT_KEYS, r, strict=True)) for r in rows]
        for d in out:
            d["detail"] = None if d["detail"] is None else json.loads(d["detail"])
        return out

    def is_artifact(self, path: str) -> bool:
        """True when ``path`` is an image path some stored layer result refers to."""
        return self._run(lambda db: db.execute("SELECT 1 FROM artifacts WHERE path = ?", (str(path),)).fetchone()) is not None

    def set_setting(self, name: str, value: Any) -> None:
        """Store (or replace) the JSON-able ``value`` under ``name`` (e.g. ``"job_config"``); one transaction."""
        text = json.dumps(value.model_dump(mode="json") if hasattr(value, "model_dump") else value)

        def fn(db: sqlite3.Connection) -> None:
            db.execute(
                "INSERT INTO settings(name, value, updated) VALUES (?, ?, ?) "
                "ON CONFLICT(name) DO UPDATE SET value=excluded.value, updated=excluded.updated",
                (str(name), text, time.time()),
            )

        self._run(fn, write=True)

    def setting(self, name: str) -> Any | None:
        """The value stored under ``name`` (as decoded JSON), or ``None`` if never set."""
        row = self._run(lambda db: db.execute("SELECT value FROM settings WHERE name = ?", (str(name),)).fetchone())
        return None if row is None else json.loads(row[0])

    # -- reading ------------------------------------------------------------------
    @staticmethod
    def _job_row(row: tuple) -> dict[str, Any]:
        d = dict(zip(_JOB_KEYS, row, strict=True))
        d["config"] = None if d["config"] is None else json.loads(d["config"])
        return d

    def jobs(self) -> list[dict[str, Any]]:
        """All jobs, newest first, each with ``n_layers`` and ``max_anomaly_ratio``."""

        def fn(db: sqlite3.Connection) -> list[dict[str, Any]]:
            rows = db.execute(
                f"SELECT {_JOB_COLS}, COUNT(l.layer), MAX(l.anomaly_ratio) FROM jobs j "
                "JOIN printers p ON p.id = j.printer_id LEFT JOIN layers l ON l.job_id = j.id "
                "GROUP BY j.id ORDER BY j.id DESC"
            ).fetchall()
            out = []
            for r in rows:
                d = self._job_row(r[:9])
                d.pop("config")
                d["n_layers"], d["max_anomaly_ratio"] = int(r[9]), r[10]
                out.append(d)
            return out

        return self._run(fn)

    def last_job_id(self) -> int | None:
        """Id of the newest job (one indexed read), or ``None`` when there is none."""
        return self._run(lambda db: db.execute("SELECT MAX(id) FROM jobs").fetchone()[0])

    def job(self, job_id: int) -> dict[str, Any] | None:
        """One job as a dict (config and ``last_layer`` included), or ``None`` if unknown."""

        def fn(db: sqlite3.Connection) -> dict[str, Any] | None:
            r = db.execute(
                f"SELECT {_JOB_COLS}, (SELECT MAX(layer) FROM layers WHERE job_id = j.id) "
                "FROM jobs j JOIN printers p ON p.id = j.printer_id WHERE j.id = ?",
                (_int(job_id),),
            ).fetchone()
            if r is None:
                return None
            d = self._job_row(r[:9])
            d["last_layer"] = r[9]
            return d

        return self._run(fn)

    def layers(self, job_id: int) -> list[LayerResult]:
        """The job's layer results ordered by layer index."""
        rows = self._run(
            lambda db: db.execute(
                "SELECT result FROM layers WHERE job_id = ? ORDER BY layer", (_int(job_id),)
            ).fetchall()
        )
        return [LayerResult.from_json(r[0]) for r in rows]

    def latest_layer(self, job_id: int) -> LayerResult | None:
        """The job's highest-index layer result, or ``None`` (one indexed row read)."""
        row = self._run(
            lambda db: db.execute(
                "SELECT result FROM layers WHERE job_id = ? ORDER BY layer DESC LIMIT 1", (_int(job_id),)
            ).fetchone()
        )
        return None if row is None else LayerResult.from_json(row[0])

    def layer_summary(self, job_id: int, after: int = -1) -> list[dict[str, Any]]:
        """Light rows ``{layer, z, anomaly_ratio, status, metric, threshold}`` for curves."""
        rows = self._run(
            lambda db: db.execute(
                "SELECT layer, z, anomaly_ratio, status, metric, threshold FROM layers "
                "WHERE job_id = ? AND layer > ? ORDER BY layer",
                (_int(job_id), _int(after)),
            ).fetchall()
        )
        keys = ("layer", "z", "anomaly_ratio", "status", "metric", "threshold")
        return [dict(zip(keys, r, strict=True)) for r in rows]

    def events(self, job_id: int, after: int = 0) -> list[dict[str, Any]]:
        """Events of a job in order (``after``: only ids greater than this)."""
        rows = self._run(
            lambda db: db.execute(
                "SELECT id, time, kind, message, data FROM events WHERE job_id = ? AND id > ? ORDER BY id",
                (_int(job_id), _int(after)),
            ).fetchall()
        )
        return [
            {"id": r[0], "time": r[1], "kind": r[2], "message": r[3], "data": None if r[4] is None else json.loads(r[4])}
            for r in rows
        ]

    def revision(self) -> tuple[int, int, float]:
        """A cheap value that changes whenever anything is written (for live updates)."""
        return self._run(
            lambda db: db.execute(
                "SELECT (SELECT COUNT(*) FROM layers), (SELECT COALESCE(MAX(id), 0) FROM events), "
                "(SELECT COALESCE(MAX(created), 0) FROM layers) + "
                "(SELECT COALESCE(SUM(COALESCE(ended, 0)), 0) + COUNT(*) FROM jobs)"
            ).fetchone()
        )
