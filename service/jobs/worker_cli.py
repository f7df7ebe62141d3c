"""``svrnet-worker``: reconstruction workers against the Redis queue, on any machine that mounts the
shared ``SVRNET_DATA_DIR`` and has the models.

Settings are the service's ``SVRNET_*`` variables (``SVRNET_QUEUE_URL`` is required); options:

* ``--workers N``: N worker processes (default 1), each forking a work horse per job;
* ``--burst``: stop once the queue is empty (batch machines, tests);
* ``--health``: exit 0 when a worker of this host is registered and heart-beating (container health
  checks), 1 otherwise.

Signals: the first SIGTERM (or Ctrl-C) lets the running job finish, then the worker exits (RQ's warm
shutdown); a second one stops the job at once and hands it back to the queue. After ``kill -9`` of a
worker its horse exits too, and the job is re-delivered to another worker once the lost worker has
been silent ``SVRNET_WORKER_LOST_AFTER_S`` (beyond its heartbeat); after ``SVRNET_JOB_MAX_ATTEMPTS``
runs it fails with that reason. Nothing is silently lost.
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import os
import signal
import socket
import sys
import time
from datetime import datetime, timezone

import redis
from rq import Queue
from rq.exceptions import StopRequested
from rq.job import Job as RqJob
from rq.worker import Worker

from service.core import logging as service_logging
from service.core.process_pools import watch_parent
from service.core.settings import Settings, load_settings, warn_unknown_variables
from service.core.threads import limit_blas_threads
from service.jobs.rq_runner import worker_context, set_context

log = logging.getLogger(__name__)


RESTART_DELAY_S = 5.0
"""How long the pool waits before it starts a worker that ended unasked again (a Redis outage: the new
worker's first connection may fail too, and is tried again as long)."""
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
_early_stops: list[int] = []


def _remember_stop(signum: int, frame: object) -> None:  # noqa: ARG001
    """Until RQ's handlers are in place, a stop signal is only remembered (see :class:`SvrnetWorker`)."""
    _early_stops.append(signum)


def hold_stop_signals() -> None:
    """Remember stop signals instead of dying of them. A handler, not a blocked mask: a process-wide
    signal goes to any thread that does not block it (BLAS pools, the parent watch), and with the
    default action there it would kill the worker; a Python handler always runs in the main thread."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, _remember_stop)


class SvrnetWorker(Worker):
    """RQ's forking worker, declared lost after ``lost_after_s`` of silence (RQ's fixed 60 s margin
    is too long for tests and too short to be tuned per site), and safe to stop while it starts."""

    lost_after_s = 60

    def get_heartbeat_ttl(self, job: RqJob) -> int:
        return int(self.job_monitoring_interval + self.lost_after_s)

    def request_force_stop(self, signum: int, frame: object) -> None:
        """RQ's cold shutdown (a second stop signal: the horse is killed, then ``SystemExit``), with the
        job it was running handed back: queued again at the front, in the job store too, its run not
        counted as an attempt (otherwise RQ leaves it started until the worker is found lost, and the
        stop spends one of its attempts)."""
        job = self.get_current_job() if self.horse_pid else None
        try:
            super().request_force_stop(signum, frame)              # type: ignore[arg-type]
        except SystemExit:
            if job is not None:
                try:
                    self._hand_back(job)
                except Exception:  # noqa: BLE001 - the stop goes on; the job is re-delivered once the worker is found lost
                    log.warning(f"job {job.id} could not be handed back", exc_info=True, extra={"job_id": job.id})
            raise

    def _hand_back(self, job: RqJob) -> None:
        """Mark ``job`` queued in the job store (a worker that takes it claims it from there), queue it
        again at the front, then take its run out of the started registry, where RQ would later
        find it abandoned. A Redis failure between the steps is logged by the caller."""
        if not worker_context().store.hand_back(job.id):     # it ended meanwhile: nothing to hand back
            return
        Queue(job.origin, connection=self.connection).enqueue_job(job, at_front=True)
        with self.connection.pipeline() as pipe:
            self.cleanup_execution(job, pipe)
            pipe.execute()
        log.info(f"handed back job {job.id} (the worker was stopped; the run does not count)", extra={"job_id": job.id})

    def _install_signal_handlers(self) -> None:
        # RQ registers the worker before it installs its handlers, and installs them outside its
        # loop: its handler, raising StopRequested there, would end the worker without unregistering.
        # A stop that came early (remembered by hold_stop_signals) is requested as the flag the loop
        # checks before it takes a job: a warm shutdown; a second signal is RQ's cold one.
        super()._install_signal_handlers()
        while _early_stops:
            try:
                self.request_stop(_early_stops.pop(0), None)
            except StopRequested:
                self._stop_requested = True


def _preload() -> None:
    """Import what jobs use before forking, so each work horse starts at once."""
    import service.pipeline.predict  # noqa: F401
    import service.reconstruction.pipeline  # noqa: F401
    import service.jobs.worker  # noqa: F401


def worker_ttl_s(settings: Settings) -> int:
    """How long a worker's registration lives in Redis without a heartbeat (RQ's ``worker_ttl``): at
    least 30 s, as RQ's idle worker beats only when its wait for a job (the ttl less 15 s) ends."""
    return max(30, settings.worker_lost_after_s)


def build_worker(settings: Settings, name: str | None = None) -> SvrnetWorker:
    connection = redis.Redis.from_url(settings.queue_url)
    worker = SvrnetWorker([Queue(settings.queue_name, connection=connection)], connection=connection, name=name,
                          job_monitoring_interval=settings.worker_heartbeat_s,
                          maintenance_interval=max(1, int(settings.queue_maintenance_s)),
                          worker_ttl=worker_ttl_s(settings))
    worker.lost_after_s = settings.worker_lost_after_s
    return worker


def work(settings: Settings, burst: bool = False, name: str | None = None) -> None:
    """One worker in this process until SIGTERM (or, with ``burst``, until the queue is empty); its
    jobs (forked work horses) with the server's BLAS threads, beside other workers and servers."""
    hold_stop_signals()
    limit_blas_threads(settings.blas_threads)
    set_context(settings)
    build_worker(settings, name).work(burst=burst, logging_level=settings.log_level.upper())


def healthy(settings: Settings, host: str | None = None) -> bool:
    """A worker of ``host`` (default: this one) is registered and its heartbeat is recent: within its
    registration's life (:func:`worker_ttl_s`) and a heartbeat interval, so that an idle worker, which
    beats only as often as that life allows, is not taken for a dead one between two beats."""
    connection = redis.Redis.from_url(settings.queue_url, socket_timeout=5, socket_connect_timeout=5)
    host = host or socket.gethostname()
    limit = settings.worker_heartbeat_s + worker_ttl_s(settings)
    now = datetime.now(timezone.utc)
    for worker in Worker.all(connection=connection, queue=Queue(settings.queue_name, connection=connection)):
        beat = worker.last_heartbeat
        if worker.hostname == host and beat is not None:
            beat = beat if beat.tzinfo else beat.replace(tzinfo=timezone.utc)
            if (now - beat).total_seconds() < limit:
                return True
    return False


def _child(settings: Settings, burst: bool, parent: int) -> None:
    # Started holding the stop signals (see _pool) until RQ's handlers take over: a stop the pool
    # forwards before then is remembered here and honoured when they are in place. The pool cleared
    # its own remembered stops before forking and forwards them itself.
    watch_parent(parent)               # `kill -9` of svrnet-worker takes its workers (and their horses) along
    sys.exit(_logged(work, settings, burst))


def _logged(run_worker, *args: object) -> int:  # noqa: ANN001
    """``run_worker(*args)``'s exit code: 0, or 1 where it ended on an error (the queue's Redis gone, an
    address that names none), told as one JSON line (its kind and place in the code), not a traceback."""
    try:
        run_worker(*args)
    except Exception as exc:  # noqa: BLE001 - any end of a worker is logged as one line, then exits 1
        log.error("the worker stopped on an error", extra={"error_type": type(exc).__name__,
                                                           "error_at": service_logging.error_at(exc)})
        return 1
    return 0


def _pool(settings: Settings, n: int, burst: bool) -> int:
    """``n`` workers in child processes; SIGTERM/SIGINT are passed on; the exit code of the worst.

    A worker that ends before the pool is told to stop (RQ quits on an error its loop does not
    handle: the queue's Redis gone while a job runs) is started again after
    :data:`RESTART_DELAY_S` (not with ``burst``, whose workers end when the queue is empty), so
    the pool keeps its ``n`` workers through a Redis outage."""
    ctx = multiprocessing.get_context("fork")

    def start(i: int) -> multiprocessing.process.BaseProcess:
        return ctx.Process(target=_child, args=(settings, burst, os.getpid()), name=f"svrnet-worker-{i}")

    children = [start(i) for i in range(n)]
    stopping = False
    # Children inherit the held stop signals (a stop before RQ's handlers is a warm one, never a kill);
    # one that reaches the pool before it forwards is forwarded as soon as it does.
    hold_stop_signals()
    pending = _early_stops[:]                            # forwarded below, not inherited by the children
    _early_stops.clear()
    for child in children:
        child.start()

    def forward(signum: int, frame: object) -> None:  # noqa: ARG001
        nonlocal stopping
        stopping = True
        for child in children:
            if child.pid is not None and child.is_alive():
                os.kill(child.pid, signum)

    signal.signal(signal.SIGTERM, forward)
    signal.signal(signal.SIGINT, forward)
    _early_stops[:0] = pending
    while _early_stops:
        forward(_early_stops.pop(0), None)
    while any(child.is_alive() for child in children) or not (stopping or burst):
        for i, child in enumerate(children):
            child.join(timeout=0.5 / n)
            if child.exitcode is not None and not (stopping or burst):
                log.warning("worker %d ended (exit code %s) before a stop: starting it again in %.0f s",
                            i, child.exitcode, RESTART_DELAY_S)
                time.sleep(RESTART_DELAY_S)
                if not stopping:
                    children[i] = start(i)
                    children[i].start()
    return max(abs(child.exitcode or 0) for child in children)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="svrnet-worker", description="SVRnet reconstruction workers on the Redis "
                                 "queue named by SVRNET_QUEUE_URL / SVRNET_QUEUE_NAME.")
    ap.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    ap.add_argument("--burst", action="store_true", help="exit once the queue is empty")
    ap.add_argument("--name", help="worker name (one worker only; default: RQ's unique name)")
    ap.add_argument("--health", action="store_true", help="exit 0 if a worker of this host is alive")
    args = ap.parse_args(argv)
    settings = load_settings("svrnet-worker", needs_default_model=False)   # it runs the model each job names
    if not settings.queue_url:
        print("svrnet-worker: set SVRNET_QUEUE_URL=redis://host:port/db", file=sys.stderr)
        return 2
    service_logging.configure(settings.log_level, libraries=("rq",))     # RQ's lines as JSON on stderr too
    warn_unknown_variables("svrnet-worker")
    if args.health:
        try:
            return 0 if healthy(settings) else 1
        except redis.RedisError as exc:
            print(f"svrnet-worker: the queue does not answer ({type(exc).__name__})", file=sys.stderr)
            return 1
    hold_stop_signals()
    _preload()
    if args.workers <= 1:
        return _logged(work, settings, args.burst, args.name)
    return _pool(settings, args.workers, args.burst)


def run() -> None:
    """Console entry point."""
    sys.exit(main())
