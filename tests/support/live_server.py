"""A real ``svrnet-server`` (uvicorn) in a subprocess of its own process group, for the crash test, the
schemathesis run and the load benchmark: whatever it leaves behind can be found and reaped."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[2]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``svrnet-server`` in its own process group (so whatever it leaves behind can be found)."""

    def __init__(self, data_dir: Path, log: Path, **settings: str) -> None:
        self.log = open(log, "ab")  # noqa: SIM115 - closed in stop()
        self.log_path = log
        for _ in range(3):                      # a port taken between its choice and the server's bind: another
            self.port = _free_port()
            self.url = f"http://127.0.0.1:{self.port}"
            env = {**os.environ, "SVRNET_HOST": "127.0.0.1", "SVRNET_PORT": str(self.port),
                   "SVRNET_DATA_DIR": str(data_dir),
                   "SVRNET_LOG_LEVEL": "info", "SVRNET_MAX_CONCURRENT": "1",
                   "PYTHONFAULTHANDLER": "1"}                 # a crash of native code leaves its traceback
            env.update({f"SVRNET_{k.upper()}": str(v) for k, v in settings.items()})
            start = log.stat().st_size
            self.proc = subprocess.Popen([sys.executable, "-c", "from service.main import run; run()"], cwd=ROOT,
                                         env=env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
            if self._ready(start):
                return
        raise AssertionError(f"the server did not start: {log.read_text()[-3000:]}")

    def _ready(self, start: int) -> bool:
        """Whether this server, and no other process on its port, answers ``/readyz`` (its own log says it
        listens there); False when it ended (its port was taken)."""
        listening = f"Uvicorn running on {self.url} "
        deadline = time.time() + 120
        while time.time() < deadline:
            if self.proc.poll() is not None:
                return False
            if listening in self.log_path.read_bytes()[start:].decode(errors="replace"):
                try:
                    if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                        return True
                except httpx.HTTPError:
                    pass
            time.sleep(0.2)
        raise AssertionError(f"the server did not become ready: {self.log_path.read_text()[-3000:]}")

    def post(self, path: str, **kwargs: object) -> httpx.Response:
        """``httpx.post`` to this server; a connection it drops says what was there to answer: whether
        the server still runs, who listens on its port, and its log's end."""
        try:
            return httpx.post(f"{self.url}{path}", **kwargs)  # type: ignore[arg-type]
        except httpx.TransportError as exc:
            import psutil

            listening = [(c.pid, c.laddr) for c in psutil.net_connections("tcp")
                         if c.laddr and c.laddr.port == self.port and c.status == psutil.CONN_LISTEN]
            raise AssertionError(f"{exc!r}; server exit code {self.proc.poll()}, pid {self.proc.pid}; listening on "
                                 f"port {self.port}: {listening}; log: {self.log_path.read_text()[-3000:]}") from exc

    def stop(self, sig: int) -> int:
        os.kill(self.proc.pid, sig)
        code = self.proc.wait(timeout=60)
        self.log.close()
        return code

    def leftovers(self, wait_s: float = 15.0) -> list[int]:
        """Processes still in the server's process group after ``wait_s`` (empty when all are gone)."""
        deadline = time.time() + wait_s
        while True:
            pids = [int(p) for p in os.listdir("/proc") if p.isdigit() and _pgid(int(p)) == self.proc.pid]
            if not pids or time.time() > deadline:
                return pids
            time.sleep(0.2)

    def kill_group(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (not yet reaped)."""
    try:
        os.kill(pid, 0)
        return True
    except ProcessLookupError:
        return False


def gone_within(pid: int, seconds: float) -> bool:
    """Whether process ``pid`` is gone within ``seconds``; one still there then is killed."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if not alive(pid):
            return True
        time.sleep(0.1)
    os.kill(pid, signal.SIGKILL)
    return False


def _pgid(pid: int) -> int | None:
    try:
        return os.getpgid(pid)
    except (ProcessLookupError, PermissionError):
        return None


class Worker:
    """``svrnet-worker`` in its own process group, on the queue of ``env`` (``SVRNET_*`` settings)."""

    def __init__(self, log: Path, env: dict[str, str], *args: str) -> None:
        self.log = open(log, "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen([sys.executable, "-c", "from service.jobs.worker_cli import run; run()", *args],
                                     cwd=ROOT, env={**os.environ, **env}, stdout=self.log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 60) -> int | None:
        """Send ``sig``; the exit code (None if it was still running after ``timeout``, then killed)."""
        try:
            os.kill(self.proc.pid, sig)
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill_group()
            return None
        except ProcessLookupError:
            return self.proc.poll()
        finally:
            self.log.close()

    def kill_group(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def stop_all(workers: list[Worker], servers: list[Server], timeout: float = 10.0) -> None:
    """SIGTERM every worker (killed after ``timeout``) and every server, leaving no process behind."""
    for w in workers:
        w.stop(signal.SIGTERM, timeout=timeout)
    for server in servers:
        server.stop(signal.SIGTERM)
        server.kill_group()


def completions(logs: list[Path]) -> dict[str, list[tuple[int, int]]]:
    """Job id -> ``(worker index in logs, attempt)`` of every run that completed it, from the workers' logs."""
    done: dict[str, list[tuple[int, int]]] = {}
    for i, log in enumerate(logs):
        for job_id, attempt in re.findall(r"job ([0-9a-f]{32}) completed, attempt (\d+)", log.read_text()):
            done.setdefault(job_id, []).append((i, int(attempt)))
    return done
