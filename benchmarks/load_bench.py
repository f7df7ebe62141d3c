"""Load and hostile-upload benchmark against a real ``svrnet-server`` (uvicorn, the shipped default model).

Two parts, both printed as tables (and as JSON with ``--json``):

1. **single uploads** -- each hostile upload of at most 10 MB (the issue's 261 KB DICOM deflate bomb that
   inflates to 256 MB, a 10 MB gzip stream bomb, a ZIP of DICOM bombs, 32 gzip bombs in one request ...)
   and one valid phantom stack, sent alone: status, seconds, the server's peak RSS while it was answered;
2. **N concurrent clients** (default 32) sending a mix of valid stacks and hostile uploads for
   ``--seconds``: status counts (only 200 / 4xx / 429 / 503 with ``Retry-After`` are expected),
   latency percentiles, the server's peak RSS (the server and its worker processes).

    .venv/bin/python benchmarks/load_bench.py [--clients 32] [--seconds 60] [--json]

Timed claims live here, never as assertions in the tests.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import tempfile
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.core.machine import cpu_description  # noqa: E402
from service.io.volume import Volume, write_volume  # noqa: E402
from tests.support import corpus  # noqa: E402
from tests.support.live_server import Server  # noqa: E402
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine  # noqa: E402


def valid_stack(folder: Path) -> bytes:
    """A phantom stack (48 x 48 x 16) as a .nii.gz."""
    shape = (48, 48, 16)
    aff = stack_affine(2, np.eye(3), 1.5, 3.5, shape)
    img, _ = acquire_stack(*phantom_brain(3), aff, shape, 2, np.broadcast_to(np.eye(4), (16, 4, 4)))
    write_volume(Volume(img * 3.0 + 20.0, aff), folder / "stack.nii.gz")
    return (folder / "stack.nii.gz").read_bytes()


def uploads(folder: Path) -> dict[str, list]:
    """name -> the multipart files of one request (each file at most 10 MB)."""
    gz_stream = corpus.gz(corpus.nifti(np.ones((12, 10, 6))) + b"\0" * (2**30))   # 1 GB of zeros, ~1 MB
    many = corpus.gzip_bomb(200)
    return {
        "valid stack": [("stacks", ("stack.nii.gz", valid_stack(folder)))],
        "DICOM deflate bomb (256 MB)": [("stacks", ("bomb.dcm", corpus.deflate_bomb(256)))],
        "gzip stream bomb (1 GB)": [("stacks", ("stream.nii.gz", gz_stream))],
        "gzip declared bomb": [("stacks", ("declared.nii.gz", corpus.gzip_bomb(1024)))],
        "ZIP of 8 DICOM bombs": [("stacks", ("bombs.zip", corpus.zipped({f"IM{i}": corpus.deflate_bomb(200)
                                                                         for i in range(8)})))],
        "32 gzip bombs, one request": [("stacks", (f"b{i}.nii.gz", many)) for i in range(32)],
        "10 MB of random bytes": [("stacks", ("noise.nii.gz", np.random.default_rng(0).bytes(10 * 2**20)))],
    }


class RssWatch:
    """Peak RSS of the server process and all its children, sampled every 20 ms."""

    def __init__(self, pid: int) -> None:
        self.proc, self.peak, self._stop = psutil.Process(pid), 0, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                procs = [self.proc, *self.proc.children(recursive=True)]
                self.peak = max(self.peak, sum(p.memory_info().rss for p in procs if p.is_running()))
            except psutil.Error:
                pass
            time.sleep(0.02)

    def reset(self) -> None:
        self.peak = 0

    def stop(self) -> int:
        self._stop.set()
        self.thread.join()
        return self.peak


def post(url: str, files: list, route: str = "/v1/predict") -> tuple[int, float, bool]:
    t0 = time.perf_counter()
    r = httpx.post(url + route, files=files, data={"mc_samples": "10"}, timeout=300)
    return r.status_code, time.perf_counter() - t0, "retry-after" in r.headers


def single_uploads(server: Server, watch: RssWatch, cases: dict[str, list]) -> list[dict]:
    rows = []
    for name, files in cases.items():
        size = sum(len(f[1][1]) for f in files)
        time.sleep(0.5)
        watch.reset()
        status, seconds, _ = post(server.url, files)
        time.sleep(0.2)
        rows.append({"upload": name, "bytes": size, "status": status, "seconds": round(seconds, 2),
                     "peak_rss_mb": round(watch.peak / 2**20)})
    return rows


def concurrent(server: Server, watch: RssWatch, cases: dict[str, list], clients: int, seconds: float) -> dict:
    mix = list(cases.items())
    stop = time.time() + seconds
    results: list[tuple[int, float, bool, str]] = []
    lock = threading.Lock()

    def client(i: int) -> None:
        k = i
        while time.time() < stop:
            route = "/v1/reconstructions" if k % 5 == 4 else "/v1/predict"
            j = k % len(mix) if route == "/v1/predict" else 1 + k % (len(mix) - 1)
            status, seconds, retry = post(server.url, mix[j][1], route)
            with lock:
                results.append((status, seconds, retry, "valid" if mix[j][0] == "valid stack" else "hostile"))
            k += clients

    watch.reset()
    with ThreadPoolExecutor(clients) as pool:
        list(pool.map(client, range(clients)))
    lat = np.array([r[1] for r in results])
    by_kind = {kind: dict(sorted(Counter(r[0] for r in results if r[3] == kind).items())) for kind in ("valid", "hostile")}
    return {"clients": clients, "requests": len(results), "status": by_kind,
            "retry_after_on_429_503": all(r[2] for r in results if r[0] in (429, 503)),
            "latency_s": {f"p{p}": round(float(np.percentile(lat, p)), 3) for p in (50, 90, 99)} | {"max": round(float(lat.max()), 3)},
            "peak_rss_mb": round(watch.peak / 2**20)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=32)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="svrnet-bench-") as tmp:
        cases = uploads(Path(tmp))
        server = Server(Path(tmp) / "data", Path(tmp) / "server.log", max_concurrent="2")
        try:
            watch = RssWatch(server.proc.pid)
            idle = psutil.Process(server.proc.pid).memory_info().rss
            singles = single_uploads(server, watch, cases)
            load = concurrent(server, watch, cases, args.clients, args.seconds)
            watch.stop()
            alive = server.proc.poll() is None and httpx.get(server.url + "/healthz").status_code == 200
            server.stop(signal.SIGTERM)
            left = server.leftovers()
        finally:
            server.kill_group()
    report = {"machine": cpu_description(), "idle_rss_mb": round(idle / 2**20), "single_uploads": singles,
              "concurrent": load, "healthy_after": alive, "processes_left_after_sigterm": len(left)}
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"machine: {report['machine']}")
    print(f"server idle RSS: {report['idle_rss_mb']} MB")
    print(f"{'upload':32} {'bytes':>10} {'status':>6} {'seconds':>8} {'peak RSS MB':>12}")
    for row in singles:
        print(f"{row['upload']:32} {row['bytes']:>10} {row['status']:>6} {row['seconds']:>8} {row['peak_rss_mb']:>12}")
    print(f"\n{load['clients']} concurrent clients, {args.seconds:.0f} s: {load['requests']} requests")
    print(f"  status counts, valid stacks: {load['status']['valid']}; hostile uploads: {load['status']['hostile']}")
    print(f"  Retry-After on every 429/503: {load['retry_after_on_429_503']}")
    print(f"  latency: {load['latency_s']}")
    print(f"  peak RSS (server + workers): {load['peak_rss_mb']} MB")
    print(f"healthy after: {alive}; processes left after SIGTERM: {len(left)}")


if __name__ == "__main__":
    main()
