"""``POST /v1/predict`` over real HTTP: a uvicorn server on 127.0.0.1, timings by stage, peak RSS.

Scenarios (stacks cut from an atlas volume at three orthogonal orientations with motion, masks
uploaded, N4 on, 100 MC samples), each with and without ``image_consistency`` (the ratio printed):
  A. three stacks of 128 x 128 x 35 (target <= 2 s);
  B. six stacks of 320 x 320 x 22 (target <= 5 s).

    .venv/bin/python benchmarks/predict_bench.py [--model-dir service/models]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.geometry import se3  # noqa: E402
from service.io.volume import Volume, read_volume, write_volume  # noqa: E402
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine  # noqa: E402

ATLAS = ROOT.parent / "shared" / "data" / "fetal_atlas" / "crl_sta"


def brain() -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    if (ATLAS / "STA30_T2.nii.gz").exists():
        img, msk = read_volume(ATLAS / "STA30_T2.nii.gz"), read_volume(ATLAS / "STA30_mask.nii.gz")
        return img.array, msk.array, img.affine, "atlas STA30"
    return (*phantom_brain(0), "phantom")


def make_stacks(folder: Path, n: int, shape_inplane: int, n_slices: int, inplane_mm: float) -> list[tuple[Path, Path]]:
    img, msk, aff, _ = brain()
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        axis = i % 3
        shape = [shape_inplane] * 3
        shape[axis] = n_slices
        rot = se3.so3_exp(rng.normal(scale=0.2, size=3))
        a = stack_affine(axis, rot, inplane_mm, 3.5, tuple(shape), centre_mm=(0.0, 2.0, 8.0))
        g = se3.exp(np.concatenate([rng.normal(scale=0.05, size=(n_slices, 3)), rng.normal(scale=1.5, size=(n_slices, 3))], 1))
        s, m = acquire_stack(img, msk, aff, a, tuple(shape), axis, g)
        field = np.linspace(0.8, 1.2, shape[0])[:, None, None]
        paths = (folder / f"stack{i}.nii.gz", folder / f"mask{i}.nii.gz")
        write_volume(Volume((s * field + rng.normal(scale=5, size=s.shape)).astype(np.float32), a), paths[0])
        write_volume(Volume(m.astype(np.uint8), a), paths[1])
        out.append(paths)
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024
    return float("nan")


def run(client: httpx.Client, stacks: list[tuple[Path, Path]], repeats: int = 3, **form: str) -> tuple[float, dict]:
    files = [("stacks", (p.name, p.read_bytes())) for p, _ in stacks] + [("masks", (m.name, m.read_bytes())) for _, m in stacks]
    best, timing = float("inf"), {}
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = client.post("/v1/predict", files=files, data={"mc_samples": "100", **form})
        wall = time.perf_counter() - t0
        r.raise_for_status()
        if wall < best:
            best, timing = wall, r.json()["timing_ms"]
    return best, timing


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model-dir", default=str(ROOT / "service" / "models"))
    args = ap.parse_args()
    port = free_port()
    env = dict(os.environ, SVRNET_PORT=str(port), SVRNET_MODELS_DIR=args.model_dir, SVRNET_LOG_LEVEL="warning")
    server = subprocess.Popen([sys.executable, "-c", "from service.main import run; run()"], env=env, cwd=ROOT)
    try:
        with tempfile.TemporaryDirectory() as tmp, httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=300) as client:
            (Path(tmp) / "b").mkdir()
            a = make_stacks(Path(tmp), 3, 128, 35, 1.1)
            b = make_stacks(Path(tmp) / "b", 6, 320, 22, 0.55)
            for _ in range(100):
                try:
                    if client.get("/readyz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                time.sleep(0.2)
            print(f"source: {brain()[3]}; server pid {server.pid} on 127.0.0.1:{port}")
            for name, stacks, target in (("A: 3 x 128x128x35", a, 2.0), ("B: 6 x 320x320x22", b, 5.0)):
                walls = {}
                for image in ("true", "false"):
                    wall, t = run(client, stacks, image_consistency=image)
                    walls[image] = wall
                    stages = ", ".join(f"{k} {v:.0f}" for k, v in t.items() if k != "total")
                    print(f"{name}, image_consistency={image}: {wall:.2f} s wall over HTTP (target <= {target:.0f} s); "
                          f"server total {t['total']:.0f} ms")
                    print(f"   stages (ms; localisation and N4 are summed over stacks run in parallel): {stages}")
                print(f"   image consistency costs x{walls['true'] / walls['false']:.2f} of the request without it")
            print(f"peak RSS of the server: {peak_rss_mb(server.pid):.0f} MB (target <= 2048 MB)")
    finally:
        server.terminate()
        server.wait(10)


if __name__ == "__main__":
    main()
