"""The distributed back-end's job records: one Redis hash per job, one sorted set per state.

Every API replica and every worker reads and writes the same records, so a job submitted through
one replica is polled through another. Each transition is one Lua script (atomic in Redis): a job is
claimed by one worker at a time, a cancelled job never ends ``succeeded``, a finished one never
changes again. Files stay on the shared ``data_dir`` (see :class:`~service.jobs.store.JobStore`).

Keys, under ``svrnet:<queue name>:``: ``job:<id>`` (hash), ``state:<status>`` (sorted set: by
creation for ``queued``/``running``, by last change for the final states, which retention reads).

Example (needs a Redis server):
    >>> store = RedisJobStore("redis://127.0.0.1:6379/0", Path("/srv/svrnet-data"))  # doctest: +SKIP
    >>> store.claim(store.create({"resolution_mm": 0.8}).id)  # doctest: +SKIP
    1
"""

from __future__ import annotations

import functools
import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import redis

from service.core.errors import StoreUnavailable
from service.jobs.store import FINAL, STATES, SUBMISSION_LEASE_S, Job, JobStore

F = TypeVar("F", bound=Callable)

# KEYS: the job's hash, then the state sets in the order of STATES. ARGV: job id, the states it may
# leave (space-separated), the new state, now, the attempt the job must be at ("" for any), then
# field/value pairs ("+field" increments). Returns the job's attempts after the move, -1 if refused.
TRANSITION = """
local status = redis.call('HGET', KEYS[1], 'status')
if not status then return -1 end
local allowed = false
for s in string.gmatch(ARGV[2], '%S+') do if s == status then allowed = true end end
if not allowed then return -1 end
if ARGV[5] ~= '' and redis.call('HGET', KEYS[1], 'attempts') ~= ARGV[5] then return -1 end
local states = {queued = 2, running = 3, succeeded = 4, failed = 5, cancelled = 6}
redis.call('HSET', KEYS[1], 'status', ARGV[3], 'updated_at', ARGV[4])
for i = 6, #ARGV, 2 do
  if string.sub(ARGV[i], 1, 1) == '+' then
    redis.call('HINCRBY', KEYS[1], string.sub(ARGV[i], 2), ARGV[i + 1])
  else
    redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1])
  end
end
redis.call('ZREM', KEYS[states[status]], ARGV[1])
local score = ARGV[4]
if ARGV[3] == 'queued' or ARGV[3] == 'running' then score = redis.call('HGET', KEYS[1], 'created_at') end
redis.call('ZADD', KEYS[states[ARGV[3]]], score, ARGV[1])
return tonumber(redis.call('HGET', KEYS[1], 'attempts'))
"""

# KEYS: the job's hash. ARGV: field/value pairs, set only if the job exists.
UPDATE = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
if ARGV[1] ~= '' and redis.call('HGET', KEYS[1], 'status') ~= ARGV[1] then return 0 end
for i = 2, #ARGV, 2 do redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1]) end
return 1
"""

def _job(values: dict[str, str]) -> Job:
    """A :class:`Job` from the strings of its hash."""
    return Job(id=values["id"], status=values["status"], stage=values.get("stage"),
               progress=float(values.get("progress", 0.0)), error=values.get("error"),
               params=json.loads(values["params"]), report=json.loads(values["report"]) if "report" in values else None,
               attempts=int(values.get("attempts", 0)), created_at=float(values["created_at"]),
               updated_at=float(values["updated_at"]),
               submitted_at=float(values["submitted_at"]) if "submitted_at" in values else None,
               started_at=float(values["started_at"]) if "started_at" in values else None)


def _answering(method: F) -> F:
    """Redis not answering becomes :class:`StoreUnavailable` (a 503 with ``Retry-After``), not a 500."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):  # noqa: ANN001, ANN202
        try:
            return method(self, *args, **kwargs)
        except redis.RedisError as exc:
            raise StoreUnavailable("the job store (Redis) does not answer; retry later", 5) from exc

    return wrapper  # type: ignore[return-value]


class RedisJobStore(JobStore):
    """Job records in Redis at ``url`` (namespace ``svrnet:<queue_name>``); files under ``data_dir``,
    a folder every API replica and worker mounts."""

    def __init__(self, url: str, data_dir: Path, queue_name: str = "svrnet") -> None:
        self.data_dir = Path(data_dir)
        (self.data_dir / "jobs").mkdir(parents=True, exist_ok=True)
        self.redis = redis.Redis.from_url(url, decode_responses=True, socket_timeout=10, socket_connect_timeout=5,
                                          health_check_interval=30)
        self.prefix = f"svrnet:{queue_name}:"
        self._transition = self.redis.register_script(TRANSITION)
        self._update = self.redis.register_script(UPDATE)

    def _key(self, job_id: str) -> str:
        return f"{self.prefix}job:{job_id}"

    def _state_keys(self) -> list[str]:
        return [f"{self.prefix}state:{s}" for s in STATES]

    def _move(self, job_id: str, allowed: tuple[str, ...], to: str, attempt: int | None = None,
              **fields: object) -> int:
        """The transition script: the job's attempts after the move, -1 if refused."""
        args = [job_id, " ".join(allowed), to, repr(time.time()), "" if attempt is None else str(attempt)]
        for k, v in fields.items():
            args += [k, v if isinstance(v, str) else json.dumps(v)]
        return int(self._transition(keys=[self._key(job_id), *self._state_keys()], args=args))

    def ping(self) -> bool:
        """Whether Redis answers and the shared jobs' folder can take jobs (:meth:`folders_take_jobs`: a
        volume mounted read-only, full or gone answers the status routes and fails every submission)."""
        try:
            if not self.redis.ping():
                return False
        except redis.RedisError:
            return False
        return self.folders_take_jobs()

    @_answering
    def create(self, params: dict, map_key: bool = True, max_queued: int | None = None) -> Job:
        """A new ``queued`` job; with ``map_key``, its idempotency key (if any) names it from now on;
        :class:`~service.core.errors.QueueFull` where ``max_queued`` jobs are queued already (counted
        and added in one transaction: Redis runs it only if no job entered or left the queue
        meanwhile, else it is tried again)."""
        queued = f"{self.prefix}state:queued"
        with self._new_job() as job_id, self.redis.pipeline(transaction=True) as pipe:
            while True:
                try:
                    if max_queued is not None:
                        pipe.watch(queued)
                        if pipe.zcard(queued) >= max_queued:
                            pipe.reset()
                            raise self._queue_full(job_id, max_queued)
                        pipe.multi()
                    now = repr(time.time())
                    pipe.hset(self._key(job_id), mapping={"id": job_id, "status": "queued", "stage": "queued",
                                                          "progress": "0", "params": json.dumps(params),
                                                          "attempts": "0", "created_at": now, "updated_at": now})
                    pipe.zadd(queued, {job_id: float(now)})
                    if map_key and params.get("idempotency_key"):
                        pipe.set(self._idempotency(params["idempotency_key"]), job_id)
                    pipe.execute()
                    break
                except redis.WatchError:
                    continue
        return self.get(job_id)  # type: ignore[return-value]

    @_answering
    def create_once(self, params: dict, max_queued: int | None = None) -> tuple[Job, bool]:
        key = params.get("idempotency_key")
        if not key:
            return self.create(params, max_queued=max_queued), True
        made = self.create(params, map_key=False, max_queued=max_queued)
        if self.redis.set(self._idempotency(key), made.id, nx=True):      # the key is this job's
            return made, True
        earlier = self.job_for_key(key)
        if earlier is None:                                              # its job was deleted meanwhile
            self.redis.set(self._idempotency(key), made.id)
            return made, True
        with self.redis.pipeline(transaction=True) as pipe:              # another submission's: ours goes
            pipe.zrem(f"{self.prefix}state:queued", made.id)
            pipe.delete(self._key(made.id))
            pipe.execute()
        shutil.rmtree(self.directory(made.id), ignore_errors=True)
        return earlier, False

    def _idempotency(self, key: str) -> str:
        return f"{self.prefix}idempotency:{key}"

    @_answering
    def job_for_key(self, key: str) -> Job | None:
        job_id = self.redis.get(self._idempotency(key))
        return None if job_id is None else self.get(job_id)

    @_answering
    def get(self, job_id: str) -> Job | None:
        values = self.redis.hgetall(self._key(job_id))
        return _job(values) if values else None

    @_answering
    def update(self, job_id: str, **fields: object) -> None:
        if not set(fields) <= {"stage", "progress", "submitted_at"}:
            raise ValueError(f"update: only stage, progress, submitted_at (not {sorted(fields)})")
        progress = bool({"stage", "progress"} & set(fields))   # a change; the queue's hand-over time is not
        args: list[str] = ["running", "updated_at", repr(time.time())] if progress else [""]
        for k, v in fields.items():
            args += [k, v if isinstance(v, str) else repr(float(v))]  # type: ignore[arg-type]
        self._update(keys=[self._key(job_id)], args=args)

    @_answering
    def claim(self, job_id: str, redelivered: bool = False) -> int:
        allowed = ("queued", "running") if redelivered else ("queued",)
        return max(0, self._move(job_id, allowed, "running", stage="starting", progress="0",
                                 started_at=repr(time.time()), **{"+attempts": 1}))

    @_answering
    def hand_back(self, job_id: str) -> bool:
        """Put a running job back in the queue (its worker was stopped at once): its run does not
        count as an attempt. False where it was no longer running (it ended meanwhile)."""
        return self._move(job_id, ("running",), "queued", stage="queued (handed back by a stopping worker)",
                          progress="0", **{"+attempts": -1}) >= 0

    @_answering
    def hold_submission(self, job_id: str) -> None:
        self.redis.set(f"{self.prefix}submitting:{job_id}", "1", px=int(SUBMISSION_LEASE_S * 1000))

    @_answering
    def submission_held(self, job_id: str) -> bool:
        return bool(self.redis.exists(f"{self.prefix}submitting:{job_id}"))

    @_answering
    def back_in_queue(self, job_id: str, attempt: int) -> bool:
        """Show a running job as queued again where the queue put it back after its worker was lost
        (the lost run counts: the queue's retry took one of its attempts). Only the run ``attempt``:
        a later run that has claimed it meanwhile is left running. False where the move did not apply."""
        return self._move(job_id, ("running",), "queued", attempt, stage="queued (its worker was lost)",
                          progress="0") >= 0

    @_answering
    def finish(self, job_id: str, report: dict, attempt: int | None = None) -> bool:
        allowed = ("running",) if attempt is None else ("running", "queued")     # queued: put back under this run
        return self._move(job_id, allowed, "succeeded", attempt, stage="done", progress="1.0", report=report) >= 0

    @_answering
    def fail(self, job_id: str, reason: str, attempt: int | None = None) -> bool:
        return self._move(job_id, ("queued", "running"), "failed", attempt, stage="failed", error=reason) >= 0

    @_answering
    def cancel(self, job_id: str) -> bool:
        if self._move(job_id, ("queued", "running"), "cancelled", stage="cancelled") < 0:
            return False
        shutil.rmtree(self.directory(job_id), ignore_errors=True)
        return True

    @_answering
    def delete(self, job_id: str) -> None:
        job = self.get(job_id)
        with self.redis.pipeline(transaction=True) as pipe:
            key = job.params.get("idempotency_key") if job is not None else None
            if key and self.redis.get(self._idempotency(key)) == job_id:     # not a later job's of the same key
                pipe.delete(self._idempotency(key))
            for key in self._state_keys():
                pipe.zrem(key, job_id)
            pipe.delete(self._key(job_id))
            pipe.execute()
        shutil.rmtree(self.directory(job_id), ignore_errors=True)

    @_answering
    def ids(self, status: str) -> list[str]:
        return list(self.redis.zrange(f"{self.prefix}state:{status}", 0, -1))

    @_answering
    def counts(self) -> dict[str, int]:
        with self.redis.pipeline(transaction=False) as pipe:
            for key in self._state_keys():
                pipe.zcard(key)
            return dict(zip(STATES, pipe.execute()))

    @_answering
    def expire(self, retention_s: float) -> list[str]:
        cutoff = time.time() - retention_s
        ids = [i for s in FINAL for i in self.redis.zrangebyscore(f"{self.prefix}state:{s}", "-inf", cutoff)]
        for job_id in ids:
            self.delete(job_id)
        return ids
