"""The embedded job store: job records in SQLite (``<data_dir>/jobs.sqlite3``, WAL, safe across the
server's worker processes), files in ``<data_dir>/jobs/<id>/`` as for every back-end
(:class:`~service.jobs.store.JobStore`).

After a restart of the embedded server, :meth:`SqliteJobStore.recover` puts jobs that were
``running`` back to ``queued`` (they are re-run from their stored inputs; after ``max_attempts`` they
fail with a reason), so no job is silently lost.

Example:
    >>> import tempfile
    >>> store = SqliteJobStore(Path(tempfile.mkdtemp()))
    >>> job = store.create({"resolution_mm": 0.8})
    >>> store.get(job.id).status
    'queued'
    >>> store.claim(job.id), store.claim(job.id)
    (1, 0)
"""

from __future__ import annotations

import json
import logging
import shutil
import sqlite3
import time
from collections.abc import Iterator
from contextlib import closing, contextmanager
from pathlib import Path

from service.core.errors import StoreUnavailable
from service.jobs.runner import lost_worker
from service.jobs.store import FIELDS, Job, JobStore

log = logging.getLogger(__name__)
SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    status TEXT NOT NULL,
    stage TEXT,
    progress REAL NOT NULL DEFAULT 0,
    error TEXT,
    params TEXT NOT NULL,
    report TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    created_at REAL NOT NULL,
    updated_at REAL NOT NULL,
    submitted_at REAL,
    started_at REAL
)
"""


INSERT_JOB = ("INSERT INTO jobs (id, status, stage, progress, params, created_at, updated_at) "
              "VALUES (?, 'queued', 'queued', 0, ?, ?, ?)")
"""A new queued job."""
KEY_QUERY = "SELECT id FROM jobs WHERE json_extract(params, '$.idempotency_key') = ? ORDER BY created_at DESC LIMIT 1"
"""The latest job created with an idempotency key."""


class SqliteJobStore(JobStore):
    """The embedded back-end: jobs in ``<data_dir>/jobs.sqlite3`` (WAL, safe across the server's
    worker processes); files in ``<data_dir>/jobs/<id>/``."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = Path(data_dir)
        (self.data_dir / "jobs").mkdir(parents=True, exist_ok=True)
        self.db_path = self.data_dir / "jobs.sqlite3"
        with self._db() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute(SCHEMA)
            cols = {r["name"] for r in db.execute("PRAGMA table_info(jobs)")}
            for col in ("submitted_at", "started_at"):       # a database without these columns
                if col not in cols:
                    db.execute(f"ALTER TABLE jobs ADD COLUMN {col} REAL")

    @contextmanager
    def _db(self) -> Iterator[sqlite3.Connection]:
        """A connection, closed when the block ends (an sqlite3 connection refers to itself through
        its statement cache: dropped, it would keep its file open until a garbage collection, which
        an idle server seldom runs while its upkeep opens more); a database that cannot be read or
        written (a read-only or full disk, a damaged file) is
        :class:`~service.core.errors.StoreUnavailable` (503), never a traceback."""
        try:
            with closing(sqlite3.connect(self.db_path, timeout=30, isolation_level=None)) as db:
                db.row_factory = sqlite3.Row
                db.execute("PRAGMA secure_delete=ON")    # a deleted job's pages are zeroed, not left in free space
                with db:
                    yield db
        except sqlite3.Error as exc:
            raise StoreUnavailable(f"the job store's database cannot be used ({exc})") from exc

    def _write(self, sql: str, args: tuple) -> bool:
        with self._db() as db:
            return db.execute(sql, args).rowcount == 1

    def ping(self) -> bool:
        """Whether the database answers and it and the jobs' folder can be written (a read-only data
        folder answers reads and fails every submission)."""
        try:
            with self._db() as db:
                db.execute("SELECT 1 FROM jobs LIMIT 1").fetchone()
        except StoreUnavailable:
            return False
        return self.folders_take_jobs(self.db_path)

    def create(self, params: dict) -> Job:
        with self._new_job() as job_id:
            now = time.time()
            self._write(INSERT_JOB, (job_id, json.dumps(params), now, now))
        return self.get(job_id)  # type: ignore[return-value]

    def create_once(self, params: dict, max_queued: int | None = None) -> tuple[Job, bool]:
        key = params.get("idempotency_key")
        if not key and max_queued is None:
            return self.create(params), True
        with self._new_job() as job_id, self._db() as db:
            now = time.time()
            db.execute("BEGIN IMMEDIATE")             # the checks and the insert, one writer at a time
            try:
                row = db.execute(KEY_QUERY, (key,)).fetchone() if key else None
                full = row is None and max_queued is not None and db.execute(
                    "SELECT COUNT(*) FROM jobs WHERE status = 'queued'").fetchone()[0] >= max_queued
                if row is None and not full:
                    db.execute(INSERT_JOB, (job_id, json.dumps(params), now, now))
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:              # SQLite rolls back by itself on some errors (a full disk)
                    db.execute("ROLLBACK")
                raise
        if full:
            raise self._queue_full(job_id, max_queued)  # type: ignore[arg-type]
        if row is not None:                               # another submission's job: the id drawn for this one goes
            shutil.rmtree(self.directory(job_id), ignore_errors=True)
        return (self.get(job_id), True) if row is None else (self.get(row["id"]), False)  # type: ignore[return-value]

    def job_for_key(self, key: str) -> Job | None:
        with self._db() as db:
            row = db.execute(KEY_QUERY, (key,)).fetchone()
        return None if row is None else self.get(row["id"])

    def get(self, job_id: str) -> Job | None:
        with self._db() as db:
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            return None
        values = {k: row[k] for k in FIELDS}
        values["params"] = json.loads(values["params"])
        values["report"] = json.loads(values["report"]) if values["report"] else None
        return Job(**values)

    def update(self, job_id: str, **fields: object) -> None:
        if not set(fields) <= {"stage", "progress", "submitted_at"}:
            raise ValueError(f"update: only stage, progress, submitted_at (not {sorted(fields)})")
        running = " AND status = 'running'" if {"stage", "progress"} & set(fields) else ""
        if running:                     # progress is a change; the queue's hand-over time is not (expiry reads it)
            fields["updated_at"] = time.time()
        cols = ", ".join(f"{k} = ?" for k in fields)
        self._write(f"UPDATE jobs SET {cols} WHERE id = ?{running}", (*fields.values(), job_id))

    def claim(self, job_id: str, redelivered: bool = False) -> int:
        states = "('queued', 'running')" if redelivered else "('queued')"
        now = time.time()
        with self._db() as db:
            row = db.execute("UPDATE jobs SET status = 'running', stage = 'starting', progress = 0, attempts = "
                             f"attempts + 1, started_at = ?, updated_at = ? WHERE id = ? AND status IN {states} "
                             "RETURNING attempts", (now, now, job_id)).fetchone()
        return int(row["attempts"]) if row else 0

    def finish(self, job_id: str, report: dict, attempt: int | None = None) -> bool:
        return self._write("UPDATE jobs SET status = 'succeeded', stage = 'done', progress = 1.0, report = ?, "
                           "updated_at = ? WHERE id = ? AND (status = 'running' OR (status = 'queued' AND ? IS NOT "
                           "NULL)) AND (? IS NULL OR attempts = ?)",
                           (json.dumps(report), time.time(), job_id, attempt, attempt, attempt))

    def fail(self, job_id: str, reason: str, attempt: int | None = None) -> bool:
        return self._write("UPDATE jobs SET status = 'failed', stage = 'failed', error = ?, updated_at = ? "
                           "WHERE id = ? AND status IN ('queued', 'running') AND (? IS NULL OR attempts = ?)",
                           (reason, time.time(), job_id, attempt, attempt))

    def cancel(self, job_id: str) -> bool:
        """As :meth:`JobStore.cancel`; where the store refuses the write (a full disk), the files of a
        job not yet ended go first and the write is tried again: their space is what lets it through,
        and the user asked for them to go (the run finds them gone and stops)."""
        def cancelled() -> bool:
            return self._write("UPDATE jobs SET status = 'cancelled', stage = 'cancelled', updated_at = ? "
                               "WHERE id = ? AND status IN ('queued', 'running')", (time.time(), job_id))

        try:
            done = cancelled()
        except StoreUnavailable:
            job = self.get(job_id)
            if job is None or job.status not in ("queued", "running"):
                raise
            shutil.rmtree(self.directory(job_id), ignore_errors=True)
            done = cancelled()
        if not done:
            return False
        shutil.rmtree(self.directory(job_id), ignore_errors=True)
        return True

    def delete(self, job_id: str) -> None:
        shutil.rmtree(self.directory(job_id), ignore_errors=True)     # the files first: on a full disk their space
        self._write("DELETE FROM jobs WHERE id = ?", (job_id,))      # is what lets the record's deletion write
        self._checkpoint()

    def _checkpoint(self) -> None:
        """Write the log's pages back into the database and empty the log, so that deleted jobs'
        records (their parameters, reports, idempotency keys) do not outlive them in
        ``jobs.sqlite3-wal``. It never waits: where another connection is reading or writing, the
        checkpoint gives up at once (SQLite's busy result), and a later deletion's does it."""
        try:
            db = sqlite3.connect(self.db_path, timeout=0, isolation_level=None)
            try:
                db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            finally:
                db.close()
        except sqlite3.Error:
            pass

    def ids(self, status: str) -> list[str]:
        with self._db() as db:
            return [r["id"] for r in db.execute("SELECT id FROM jobs WHERE status = ? ORDER BY created_at", (status,))]

    def recover(self, max_attempts: int = 2, cause: str = "restart", spared: list[str] = ()) -> list[str]:
        """After a restart (or, ``cause="lost worker"``, after the worker processes running them were
        lost): re-queue interrupted jobs (or fail them after ``max_attempts``, deleting their
        uploads); the queue. The jobs of ``spared`` were stopped for another job's sake (their
        processes with its): the interrupted run does not count as one of their attempts."""
        now = time.time()
        error = "interrupted by a server restart too many times" if cause == "restart" else lost_worker(max_attempts)
        with self._db() as db:
            db.executemany("UPDATE jobs SET attempts = attempts - 1 WHERE id = ? AND status = 'running' AND attempts > 0",
                           [(job_id,) for job_id in spared])
            given_up = [r["id"] for r in db.execute(
                "SELECT id FROM jobs WHERE status = 'running' AND attempts >= ?", (max_attempts,))]
            db.execute("UPDATE jobs SET status = 'failed', stage = 'failed', updated_at = ?, error = ? "
                       "WHERE status = 'running' AND attempts >= ?", (now, error, max_attempts))
            db.execute("UPDATE jobs SET status = 'queued', stage = ?, progress = 0, updated_at = ? "
                       "WHERE status = 'running'", (f"queued (re-run after {cause})", now))
        for job_id in given_up:
            self.discard_files(job_id)            # what the interrupted runs wrote of the results too
            log.warning(f"job {job_id} failed: {error}", extra={"job_id": job_id})
        return self.queued()

    def expire(self, retention_s: float) -> list[str]:
        cutoff = time.time() - retention_s
        with self._db() as db:
            ids = [r["id"] for r in db.execute(
                "SELECT id FROM jobs WHERE status IN ('succeeded', 'failed', 'cancelled') AND updated_at < ?", (cutoff,))]
        for i in ids:                  # the files first: on a full disk their space lets the records' deletion write
            shutil.rmtree(self.directory(i), ignore_errors=True)
        if ids:
            with self._db() as db:
                db.executemany("DELETE FROM jobs WHERE id = ?", [(i,) for i in ids])
            self._checkpoint()
        return ids
