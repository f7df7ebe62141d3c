"""A real ``redis-server`` for the distributed back-end's tests (no mocks, no fakeredis): started on a
free loopback port with no persistence, in a folder of its own, stopped at the end.

The binary comes from the system (Debian's ``redis-server``, which ``.ci/run`` installs) or
``SVRNET_TEST_REDIS_SERVER``; the tests that need it skip, saying so, where there is none (and fail
where ``SVRNET_TEST_REQUIRE_REDIS=1``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import redis

from tests.support.live_server import _free_port


def redis_server_binary() -> str | None:
    return os.environ.get("SVRNET_TEST_REDIS_SERVER") or shutil.which("redis-server")


SKIP_REASON = ("needs a redis-server binary (apt-get install redis-server, as .ci/run does, or set "
               "SVRNET_TEST_REDIS_SERVER) for the distributed back-end")


class RedisServer:
    """``redis-server`` on ``127.0.0.1:<free port>``; ``url`` for clients."""

    def __init__(self, folder: Path) -> None:
        binary = redis_server_binary()
        if binary is None:
            raise RuntimeError(SKIP_REASON)
        folder.mkdir(parents=True, exist_ok=True)
        self.port = _free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc = subprocess.Popen([binary, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
                                      "--appendonly", "no", "--dir", str(folder), "--daemonize", "no",
                                      "--loglevel", "warning"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        client = redis.Redis.from_url(self.url)
        deadline = time.time() + 20
        while True:
            try:
                client.ping()
                break
            except redis.ConnectionError:
                if time.time() > deadline or self.proc.poll() is not None:
                    self.stop()
                    raise RuntimeError("redis-server did not start") from None
                time.sleep(0.05)
        client.close()

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
