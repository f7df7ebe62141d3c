"""Idempotent submissions of ``POST /v1/reconstructions``: the key a client sends with a submission and
every retry of it, what a retry is answered, and the lease a replica holds while it reads one.

A client whose first answer was lost sends the submission again with the same ``Idempotency-Key``:
it gets the job the first made (:func:`made_by_key`), never a second; the same key with another
request is refused. While the first submission's files are still read, a retry is told to come
back; a replica that stopped while reading one leaves a job no replica holds
(:meth:`~service.jobs.store.JobStore.submission_held`), failed as interrupted when a retry or the
queue's upkeep finds it (:func:`unless_abandoned`).
"""

from __future__ import annotations

import asyncio
import hashlib
import json

from anyio import to_thread
from fastapi import Response

from service.api.deps import IDEMPOTENCY_HEADER
from service.api.uploads import UploadForm
from service.core.errors import KeyReused, Saturated, ServiceError
from service.jobs.store import SUBMISSION_LEASE_S, Job, JobStore

async def submission_digest(form: UploadForm, poses_text: str | None, params: dict) -> str:
    """A digest of what a submission sends: its files (names and bytes, in order), its poses and its
    options. A retry sends the same; a key sent again with another request is refused
    (:class:`~service.core.errors.KeyReused`)."""
    digest = hashlib.sha256(json.dumps(params, sort_keys=True, default=str).encode())
    for part in (*form.stacks, *form.masks):
        digest.update(b"\0" + (part.filename or "").encode() + b"\0")
        await part.seek(0)
        while chunk := await part.read(1 << 20):
            digest.update(chunk)
        await part.seek(0)
    digest.update(b"\0" + (poses_text or "").encode())
    return digest.hexdigest()


def made_by_key(earlier: Job, response: Response, retry_after_s: float, digest: str) -> dict:
    """The answer to a submission whose idempotency key made ``earlier``: that job, or 503 while the
    first submission's files are still being checked (the retry then gets the job, or its refusal);
    422 where the submission is not the one that made it (``digest``, :func:`submission_digest`)."""
    if earlier.params.get("request_digest", digest) != digest:
        raise KeyReused(f"{IDEMPOTENCY_HEADER}: this key made job {earlier.id} from another request (other files, "
                        "poses or options); send a new key with a new request")
    if earlier.status == "queued" and earlier.submitted_at is None:
        raise Saturated(f"{IDEMPOTENCY_HEADER}: the first submission with this key is still being read; send it "
                        "again after Retry-After (it answers with that job, or with why it was refused)",
                        retry_after_s=retry_after_s)
    response.headers["Location"] = f"/v1/reconstructions/{earlier.id}"          # the job this key made: not another
    return {"job_id": earlier.id, "status": earlier.status, "status_url": f"/v1/reconstructions/{earlier.id}"}


async def hold_submission(store: JobStore, job_id: str) -> None:
    """Say, every third of :data:`~service.jobs.store.SUBMISSION_LEASE_S`, that this replica still reads
    ``job_id``'s submission (until cancelled): a retry with its key then waits for it, and a replica
    that stops leaves a job that is seen as abandoned within the lease."""
    while True:
        try:
            await to_thread.run_sync(store.hold_submission, job_id)
        except ServiceError:
            pass                                      # the store briefly away: the next renewal says it
        await asyncio.sleep(SUBMISSION_LEASE_S / 3)


def unless_abandoned(store: JobStore, job: Job) -> Job:
    """``job`` as a retry with its key should see it: where its submission was never handed to the queue
    and no replica has held it for :data:`~service.jobs.store.SUBMISSION_LEASE_S` (the replica that read
    it stopped), failed as interrupted, its files gone, so that the retry is told at once (and sends a
    new key), not to wait for a submission no one reads (blocking)."""
    return (store.get(job.id) or job) if store.fail_abandoned(job, SUBMISSION_LEASE_S) else job
