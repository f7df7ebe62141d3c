"""Where jobs live: the interface every back-end honours.

States: ``queued -> running -> succeeded | failed | cancelled``. A job's uploads (``inputs/``) live
only while it is queued or running; results (``outputs/``) until the retention limit. Files are in
``<data_dir>/jobs/<id>/`` for every back-end (with the distributed one, ``data_dir`` is a volume that
every API replica and worker mounts). The distributed back-end keeps the same records in Redis
(:mod:`service.jobs.redis_store`), the embedded one in SQLite (:mod:`service.jobs.sqlite_store`);
the same tests run against both.
"""

from __future__ import annotations

import logging
import shutil
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from service.core.errors import QueueFull
from service.io.limits import folders_take_writes
from service.jobs.runner import INTERRUPTED

log = logging.getLogger(__name__)

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
FINAL = ("succeeded", "failed", "cancelled")
FIELDS = ("id", "status", "stage", "progress", "error", "params", "report", "attempts", "created_at", "updated_at",
          "submitted_at", "started_at")


SUBMISSION_LEASE_S = 30.0
"""How long a replica's word that it still reads a submission holds (:meth:`JobStore.hold_submission`;
renewed every third of it)."""
_HELD: dict[tuple[str, str], float] = {}
"""The embedded store's words that a request of this process reads a submission: (data folder, job
id) -> when it last said so. One process owns an embedded store (its file lock), so its own memory
is where they are."""


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

    def ran_longer_than(self, seconds: float, now: float | None = None) -> bool:
        """Whether the job's latest run started more than ``seconds`` ago (never where none started):
        a run past the job time limit.

        Example:
            >>> job = Job("j", "running", None, 0.0, None, {}, None, 1, 0.0, 0.0, started_at=100.0)
            >>> job.ran_longer_than(60.0, now=170.0), job.ran_longer_than(60.0, now=150.0)
            (True, False)
        """
        return self.started_at is not None and (time.time() if now is None else now) - self.started_at > seconds


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

    def discard_files(self, job_id: str) -> None:
        """Delete a job's uploads and results (``inputs/``, ``outputs/``): done when it fails or is
        cancelled, which serve no results. A run stopped from outside (the time limit, a lost or killed
        worker) may have written some of them before it stopped: they would stay, never to be served,
        until the retention limit."""
        self.discard_inputs(job_id)
        shutil.rmtree(self.directory(job_id) / "outputs", ignore_errors=True)

    def give_up(self, job_id: str, reason: str, attempt: int | None = None) -> bool:
        """Fail the job (its run ``attempt``, as :meth:`fail`) from outside its run, saying ``reason``,
        and discard what that run wrote (:meth:`discard_files`); whether it did (not where the job had
        ended, or a later run holds it). A runner's upkeep gives up a job so: past its time limit,
        lost by the queue, or whose run could not record its end.

        Example (the embedded store):
            >>> import tempfile
            >>> from service.jobs.sqlite_store import SqliteJobStore
            >>> store = SqliteJobStore(Path(tempfile.mkdtemp()))
            >>> job = store.create({}); _ = store.claim(job.id)
            >>> store.give_up(job.id, "lost", 1), store.get(job.id).error, store.give_up(job.id, "again", 1)
            (True, 'lost', False)
        """
        if not self.fail(job_id, reason, attempt):
            return False
        self.discard_files(job_id)
        log.warning(f"job {job_id} failed: {reason}", extra={"job_id": job_id})
        return True

    def discard_ended_inputs(self) -> list[str]:
        """Delete the uploads of every ended job that still has them (a worker that could not, e.g. one
        on another data folder, or one killed as the job ended), and the results of every failed or
        cancelled job that has them (:meth:`discard_files`); the ids whose files went."""
        ended = [(i, status) for status in FINAL for i in self.ids(status) if (self.directory(i) / "inputs").exists()
                 or (status != "succeeded" and (self.directory(i) / "outputs").exists())]
        for job_id, status in ended:
            if status == "succeeded":
                self.discard_inputs(job_id)
            else:
                self.discard_files(job_id)
        return [job_id for job_id, _ in ended]

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
        (called again while it does). One process owns the embedded store: it keeps the word itself
        (:data:`_HELD`), and forgets words older than the lease."""
        now = time.time()
        for key in [k for k, said in _HELD.items() if now - said > 2 * SUBMISSION_LEASE_S]:
            _HELD.pop(key, None)
        _HELD[str(self.data_dir), job_id] = now

    def submission_held(self, job_id: str) -> bool:
        """Whether a replica said within :data:`SUBMISSION_LEASE_S` that it reads ``job_id``'s
        submission; without, a job never handed to the queue was left by a replica that stopped, or
        by a request of this server whose clean-up could not delete it (a full disk)."""
        said = _HELD.get((str(self.data_dir), job_id))
        return said is not None and time.time() - said < SUBMISSION_LEASE_S

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

    @contextmanager
    def _new_job(self) -> Iterator[str]:
        """A new job's id, its folder made; the folder removed where the job's record is not written
        (a full disk, a store that does not answer): a refused submission leaves nothing behind."""
        job_id = self._new_id()
        try:
            yield job_id
        except BaseException:
            shutil.rmtree(self.directory(job_id), ignore_errors=True)
            raise

    @abstractmethod
    def ping(self) -> bool:
        """Whether the store answers and its folders can take a job (:meth:`folders_take_jobs`)."""

    def folders_take_jobs(self, *paths: Path) -> bool:
        """Whether the data folder, its jobs' folder and ``paths`` take a job
        (:func:`~service.io.limits.folders_take_writes`)."""
        return folders_take_writes(self.data_dir, self.data_dir / "jobs", *paths)

    @abstractmethod
    def create(self, params: dict) -> Job:
        """A new ``queued`` job with an empty folder."""

    @abstractmethod
    def create_once(self, params: dict, max_queued: int | None = None) -> tuple[Job, bool]:
        """:meth:`create` and True; but where a job of ``params["idempotency_key"]`` exists already,
        that job and False; :class:`~service.core.errors.QueueFull` where ``max_queued`` jobs are
        queued already. Checked and created in one step: two submissions with one key that arrive at
        the same moment make one job, and submissions that arrive together (on any replica) never
        queue more than ``max_queued``."""

    def _queue_full(self, job_id: str, max_queued: int) -> QueueFull:
        """The refusal of a job the full queue did not take (its folder, made for it, removed)."""
        shutil.rmtree(self.directory(job_id), ignore_errors=True)
        return QueueFull.holding(max_queued)

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
        the end, does not show an ended job at work), and ``updated_at`` with them alone: a job's
        hand-over to the queue, which may come after a quick job has ended, moves no ended job's
        expiry."""

    @abstractmethod
    def claim(self, job_id: str, redelivered: bool = False) -> int:
        """``queued -> running``, atomically: the run's attempt number (1, 2, ...), or 0 if the job is no
        longer queued (cancelled, finished, taken). ``redelivered``: the queue hands the job out again
        after its worker was lost, so ``running`` may be claimed too (the newer run supersedes)."""

    @abstractmethod
    def finish(self, job_id: str, report: dict, attempt: int | None = None) -> bool:
        """``running -> succeeded`` with ``report``, atomically; False if the job was cancelled meanwhile
        or (given ``attempt``) a later run has claimed it. Given ``attempt``, ``queued -> succeeded``
        too where the job was put back in the queue under that run and no run has claimed it since
        (its attempts are still ``attempt``): the queue took the run for lost (its worker silent too
        long), yet it lived on and completed the job, whose results then stand rather than being
        computed again. A job handed back by a stopping worker does not count that run (its attempts
        are one fewer), so its stopped run never finishes it."""

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
