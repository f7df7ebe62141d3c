"""The job store: one SQLite database (WAL, safe across processes) and a folder per job.

States: ``queued -> running -> succeeded | failed | cancelled``. A job's uploads (``inputs/``) live
only while it is queued or running; results (``outputs/``) until the retention limit. After a restart,
:meth:`JobStore.recover` puts jobs that were ``running`` back to ``queued`` (they are re-run from
their stored inputs; after ``max_attempts`` they fail with a reason), so no job is silently lost.

Example:
    >>> import tempfile
    >>> store = JobStore(Path(tempfile.mkdtemp()))
    >>> job = store.create({"resolution_mm": 0.8})
    >>> store.get(job.id).status
    'queued'
"""

from __future__ import annotations

import json
import shutil
import sqlite3
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
FINAL = ("succeeded", "failed", "cancelled")

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
    updated_at REAL NOT NULL
)
"""


@dataclass
class Job:
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


class JobStore:
    """Jobs in ``<data_dir>/jobs.sqlite3``; files in ``<data_dir>/jobs/<id>/``."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = Path(data_dir)
        (self.data_dir / "jobs").mkdir(parents=True, exist_ok=True)
        self.db_path = self.data_dir / "jobs.sqlite3"
        with self._connect() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute(SCHEMA)

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.db_path, timeout=30, isolation_level=None)
        db.row_factory = sqlite3.Row
        return db

    def ping(self) -> bool:
        try:
            with self._connect() as db:
                db.execute("SELECT 1").fetchone()
            return True
        except sqlite3.Error:
            return False

    def directory(self, job_id: str) -> Path:
        return self.data_dir / "jobs" / job_id

    def create(self, params: dict) -> Job:
        job_id = uuid.uuid4().hex
        now = time.time()
        self.directory(job_id).mkdir(parents=True)
        with self._connect() as db:
            db.execute("INSERT INTO jobs (id, status, stage, progress, params, created_at, updated_at) "
                       "VALUES (?, 'queued', 'queued', 0, ?, ?, ?)", (job_id, json.dumps(params), now, now))
        return self.get(job_id)  # type: ignore[return-value]

    def get(self, job_id: str) -> Job | None:
        with self._connect() as db:
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            return None
        return Job(row["id"], row["status"], row["stage"], row["progress"], row["error"], json.loads(row["params"]),
                   json.loads(row["report"]) if row["report"] else None, row["attempts"], row["created_at"],
                   row["updated_at"])

    def update(self, job_id: str, **fields: object) -> None:
        if "report" in fields and fields["report"] is not None:
            fields["report"] = json.dumps(fields["report"])
        fields["updated_at"] = time.time()
        cols = ", ".join(f"{k} = ?" for k in fields)
        with self._connect() as db:
            db.execute(f"UPDATE jobs SET {cols} WHERE id = ?", (*fields.values(), job_id))

    def claim(self, job_id: str) -> bool:
        """queued -> running, atomically; False if the job is no longer queued (cancelled, taken)."""
        with self._connect() as db:
            cur = db.execute("UPDATE jobs SET status = 'running', stage = 'starting', attempts = attempts + 1, "
                             "updated_at = ? WHERE id = ? AND status = 'queued'", (time.time(), job_id))
            return cur.rowcount == 1

    def finish(self, job_id: str, report: dict) -> bool:
        """running -> succeeded with ``report``, atomically; False if the job was cancelled meanwhile."""
        with self._connect() as db:
            cur = db.execute("UPDATE jobs SET status = 'succeeded', stage = 'done', progress = 1.0, report = ?, "
                             "updated_at = ? WHERE id = ? AND status = 'running'",
                             (json.dumps(report), time.time(), job_id))
            return cur.rowcount == 1

    def is_cancelled(self, job_id: str) -> bool:
        job = self.get(job_id)
        return job is None or job.status == "cancelled"

    def cancel(self, job_id: str) -> None:
        """Mark cancelled (a running worker stops at its next check) and delete the job's files."""
        with self._connect() as db:
            db.execute("UPDATE jobs SET status = 'cancelled', stage = 'cancelled', updated_at = ? "
                       "WHERE id = ? AND status IN ('queued', 'running')", (time.time(), job_id))
        shutil.rmtree(self.directory(job_id), ignore_errors=True)

    def delete(self, job_id: str) -> None:
        """Remove a job's row and files."""
        with self._connect() as db:
            db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))
        shutil.rmtree(self.directory(job_id), ignore_errors=True)

    def queued(self) -> list[str]:
        with self._connect() as db:
            return [r["id"] for r in db.execute("SELECT id FROM jobs WHERE status = 'queued' ORDER BY created_at")]

    def discard_inputs(self, job_id: str) -> None:
        """Delete a job's uploads (``inputs/``): done once the job has ended, whatever its outcome."""
        shutil.rmtree(self.directory(job_id) / "inputs", ignore_errors=True)

    def recover(self, max_attempts: int = 2) -> list[str]:
        """After a restart: re-queue interrupted jobs (or fail them after ``max_attempts``, deleting their
        uploads); the queue."""
        now = time.time()
        with self._connect() as db:
            given_up = [r["id"] for r in db.execute(
                "SELECT id FROM jobs WHERE status = 'running' AND attempts >= ?", (max_attempts,))]
            db.execute("UPDATE jobs SET status = 'failed', stage = 'failed', updated_at = ?, error = "
                       "'interrupted by a server restart too many times' WHERE status = 'running' AND attempts >= ?",
                       (now, max_attempts))
            db.execute("UPDATE jobs SET status = 'queued', stage = 'queued (re-run after restart)', progress = 0, "
                       "updated_at = ? WHERE status = 'running'", (now,))
        for job_id in given_up:
            self.discard_inputs(job_id)
        return self.queued()

    def expire(self, retention_s: float) -> list[str]:
        """Delete finished jobs older than ``retention_s`` (rows and files)."""
        cutoff = time.time() - retention_s
        with self._connect() as db:
            ids = [r["id"] for r in db.execute(
                "SELECT id FROM jobs WHERE status IN ('succeeded', 'failed', 'cancelled') AND updated_at < ?", (cutoff,))]
            db.executemany("DELETE FROM jobs WHERE id = ?", [(i,) for i in ids])
        for i in ids:
            shutil.rmtree(self.directory(i), ignore_errors=True)
        return ids
