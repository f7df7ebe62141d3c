"""Where jobs live: the interface every back-end honours, and the embedded one (SQLite).

States: ``queued -> running -> succeeded | failed | cancelled``. A job's uploads (``inputs/``) live
only while it is queued or running; results (``outputs/``) until the retention limit. Files are in
``<data_dir>/jobs/<id>/`` for every back-end (with the distributed one, ``data_dir`` is a volume that
every API replica and worker mounts). The distributed back-end keeps the same records in Redis
(:mod:`service.jobs.redis_store`); the same tests run against both.

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
import os
import shutil
import sqlite3
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from service.core.errors import StoreUnavailable
from service.jobs.runner import INTERRUPTED, lost_worker

log = logging.getLogger(__name__)

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
FINAL = ("succeeded", "failed", "cancelled")
FIELDS = ("id", "status", "stage", "progress", "error", "params", "report", "attempts", "created_at", "updated_at",
          "submitted_at", "started_at")


SUBMISSION_LEASE_S = 30.0
"""How long a replica's word that it still reads a submission holds (:meth:`JobStore.hold_submission`;
renewed every third of it)."""
MIN_FREE_BYTES = 64 << 20
"""The free disk a data folder must have for its store to be ready (``/readyz``): less takes no
stack of a submission."""


@dataclass
class Job:
    """One reconstruction job as every back-end stores it.

    ``submitted_at``: when its inputs were complete and it was handed to the queue; ``started_at``:
    when a worker last claimed it (the two give the queue's submit-to-start latency).
    """

    id: str
    status: str
    stage: str | None
    progress: float
    error: str | None
    params: dict
    report: dict | None
    attempts: int
    created_at: float
    updated_at: float
    submitted_at: float | None = None
    started_at: float | None = None


class JobStore(ABC):
    """The job records (state, stage, progress, report) and the job folders under ``data_dir``.

    Transitions are atomic in every back-end: a job is claimed by one worker at a time, a cancelled
    job never ends ``succeeded``, a finished one never changes again.
    """

    data_dir: Path

    def directory(self, job_id: str) -> Path:
        return self.data_dir / "jobs" / job_id

    def discard_inputs(self, job_id: str) -> None:
        """Delete a job's uploads (``inputs/``): done once the job has ended, whatever its outcome."""
        shutil.rmtree(self.directory(job_id) / "inputs", ignore_errors=True)

    def discard_ended_inputs(self) -> list[str]:
        """Delete the uploads of every ended job that still has them (a worker that could not, e.g. one
        on another data folder, or one killed as the job ended); the ids whose uploads went."""
        ended = [i for status in FINAL for i in self.ids(status) if (self.directory(i) / "inputs").exists()]
        for job_id in ended:
            self.discard_inputs(job_id)
        return ended

    def sweep_orphans(self, grace_s: float) -> list[str]:
        """Delete the job folders no record names, untouched for ``grace_s``: a record lost with a
        queue's data (a Redis restarted without persistence) or a deletion cut short would otherwise
        keep a job's uploads on disk for ever; the ids whose folders went."""
        root = self.data_dir / "jobs"
        cutoff, gone = time.time() - grace_s, []
        for folder in sorted(root.iterdir()) if root.is_dir() else []:
            try:
                stale = folder.is_dir() and folder.stat().st_mtime < cutoff
            except OSError:                     # deleted meanwhile
                continue
            if stale and self.get(folder.name) is None:
                shutil.rmtree(folder, ignore_errors=True)
                gone.append(folder.name)
        return gone

    def hold_submission(self, job_id: str) -> None:
        """Say, for :data:`SUBMISSION_LEASE_S`, that a replica is still reading ``job_id``'s submission
        (called again while it does). One process owns the embedded store: nothing to say."""

    def submission_held(self, job_id: str) -> bool:
        """Whether a replica said within :data:`SUBMISSION_LEASE_S` that it reads ``job_id``'s
        submission; without, a job never handed to the queue was left by a replica that stopped. The
        embedded store's server is the only one, and its restart recovers such jobs: always true."""
        return True

    def fail_abandoned(self, job: Job, grace_s: float) -> bool:
        """Fail ``job`` as :data:`~service.jobs.runner.INTERRUPTED`, its uploads discarded, where its
        submission was left half done: queued, never handed to the queue, made over ``grace_s`` ago
        and held by no replica (:meth:`submission_held`); whether it was. A keyed retry and the queue's
        upkeep both ask this."""
        if (job.status == "queued" and job.submitted_at is None and time.time() - job.created_at > grace_s
                and not self.submission_held(job.id) and self.fail(job.id, INTERRUPTED)):
            self.discard_inputs(job.id)
            return True
        return False

    def is_cancelled(self, job_id: str) -> bool:
        job = self.get(job_id)
        return job is None or job.status == "cancelled"

    def _new_id(self) -> str:
        job_id = uuid.uuid4().hex
        self.directory(job_id).mkdir(parents=True)
        return job_id

    @abstractmethod
    def ping(self) -> bool:
        """Whether the store answers and its folders can take a job (:meth:`folders_take_jobs`)."""

    def folders_take_jobs(self, *paths: Path) -> bool:
        """Whether the data folder and ``paths`` can be written and the disk has :data:`MIN_FREE_BYTES`
        left: a read-only folder, or a full disk, answers reads and fails every submission."""
        try:
            room = shutil.disk_usage(self.data_dir).free >= MIN_FREE_BYTES
        except OSError:
            return False
        return room and all(os.access(p, os.W_OK) for p in (*paths, self.data_dir / "jobs", self.data_dir))

    @abstractmethod
    def create(self, params: dict) -> Job:
        """A new ``queued`` job with an empty folder."""

    @abstractmethod
    def create_once(self, params: dict) -> tuple[Job, bool]:
        """:meth:`create` and True; but where a job of ``params["idempotency_key"]`` exists already,
        that job and False. Checked and created in one step: two submissions with one key that arrive
        at the same moment make one job."""

    @abstractmethod
    def get(self, job_id: str) -> Job | None:
        """The job, or None."""

    @abstractmethod
    def job_for_key(self, key: str) -> Job | None:
        """The latest job created with ``params["idempotency_key"] == key``, or None."""

    @abstractmethod
    def update(self, job_id: str, **fields: object) -> None:
        """Set ``stage``, ``progress`` or ``submitted_at`` of an existing job (never its status); a
        stage or progress only while the job runs (a run's last report, read before a cancel or
        the end, does not show an ended job at work)."""

    @abstractmethod
    def claim(self, job_id: str, redelivered: bool = False) -> int:
        """``queued -> running``, atomically: the run's attempt number (1, 2, ...), or 0 if the job is no
        longer queued (cancelled, finished, taken). ``redelivered``: the queue hands the job out again
        after its worker was lost, so ``running`` may be claimed too (the newer run supersedes)."""

    @abstractmethod
    def finish(self, job_id: str, report: dict, attempt: int | None = None) -> bool:
        """``running -> succeeded`` with ``report``, atomically; False if the job was cancelled meanwhile
        or (given ``attempt``) a later run has claimed it."""

    @abstractmethod
    def fail(self, job_id: str, reason: str, attempt: int | None = None) -> bool:
        """``queued | running -> failed`` with ``reason``; False if it had ended (e.g. was cancelled) or
        (given ``attempt``) a later run has claimed it."""

    @abstractmethod
    def cancel(self, job_id: str) -> bool:
        """Mark a queued or running job cancelled (a running worker stops at its next check) and delete
        its files; False, with nothing deleted, when it had finished meanwhile (its results stand)."""

    @abstractmethod
    def delete(self, job_id: str) -> None:
        """Remove a job's record and files."""

    @abstractmethod
    def ids(self, status: str) -> list[str]:
        """The jobs in ``status``, oldest first."""

    @abstractmethod
    def expire(self, retention_s: float) -> list[str]:
        """Delete finished jobs older than ``retention_s`` (records and files); their ids."""

    def queued(self) -> list[str]:
        return self.ids("queued")

    def counts(self) -> dict[str, int]:
        """Jobs per state (for the metrics)."""
        return {s: len(self.ids(s)) for s in STATES}


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
        """A connection; a database that cannot be read or written (a read-only or full disk, a
        damaged file) is :class:`~service.core.errors.StoreUnavailable` (503), never a traceback."""
        try:
            db = sqlite3.connect(self.db_path, timeout=30, isolation_level=None)
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
        job_id, now = self._new_id(), time.time()
        self._write(INSERT_JOB, (job_id, json.dumps(params), now, now))
        return self.get(job_id)  # type: ignore[return-value]

    def create_once(self, params: dict) -> tuple[Job, bool]:
        key = params.get("idempotency_key")
        if not key:
            return self.create(params), True
        job_id, now = self._new_id(), time.time()
        with self._db() as db:
            db.execute("BEGIN IMMEDIATE")             # the check and the insert, one writer at a time
            try:
                row = db.execute(KEY_QUERY, (key,)).fetchone()
                if row is None:
                    db.execute(INSERT_JOB, (job_id, json.dumps(params), now, now))
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise
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
                           "updated_at = ? WHERE id = ? AND status = 'running' AND (? IS NULL OR attempts = ?)",
                           (json.dumps(report), time.time(), job_id, attempt, attempt))

    def fail(self, job_id: str, reason: str, attempt: int | None = None) -> bool:
        return self._write("UPDATE jobs SET status = 'failed', stage = 'failed', error = ?, updated_at = ? "
                           "WHERE id = ? AND status IN ('queued', 'running') AND (? IS NULL OR attempts = ?)",
                           (reason, time.time(), job_id, attempt, attempt))

    def cancel(self, job_id: str) -> bool:
        if not self._write("UPDATE jobs SET status = 'cancelled', stage = 'cancelled', updated_at = ? "
                           "WHERE id = ? AND status IN ('queued', 'running')", (time.time(), job_id)):
            return False
        shutil.rmtree(self.directory(job_id), ignore_errors=True)
        return True

    def delete(self, job_id: str) -> None:
        self._write("DELETE FROM jobs WHERE id = ?", (job_id,))
        self._checkpoint()
        shutil.rmtree(self.directory(job_id), ignore_errors=True)

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
            self.discard_inputs(job_id)
            log.warning(f"job {job_id} failed: {error}", extra={"job_id": job_id})
        return self.queued()

    def expire(self, retention_s: float) -> list[str]:
        cutoff = time.time() - retention_s
        with self._db() as db:
            ids = [r["id"] for r in db.execute(
                "SELECT id FROM jobs WHERE status IN ('succeeded', 'failed', 'cancelled') AND updated_at < ?", (cutoff,))]
            db.executemany("DELETE FROM jobs WHERE id = ?", [(i,) for i in ids])
        if ids:
            self._checkpoint()
        for i in ids:
            shutil.rmtree(self.directory(i), ignore_errors=True)
        return ids
