"""``POST /v1/predict`` over real HTTP: a uvicorn server on 127.0.0.1, timings by stage, peak RSS,
and the ratio to a previous version measured in the same run.

Scenarios (stacks cut from an atlas volume at three orthogonal orientations with motion, masks
uploaded, N4 on, 100 MC samples, every stage on), each also without ``image_consistency``:
  A. three stacks of 128 x 128 x 35 (target <= 1 s);
  B. six stacks of 320 x 320 x 22 (target <= 2 s);
  R. with ``--real DIR``: a real scan's stacks and manual masks (``NAME.nii.gz`` beside
     ``NAME_brain_mask.nii.gz``, sent with ``masks_hold_csf``), and the same stacks without masks (the
     localiser's), target <= 2 s with masks and <= 1.3 x that without.

``--baseline REV`` serves the same scenarios from a git worktree of ``REV`` (its code and its
shipped models) on a second port, started beside the first, every request sent to one server and
then the other (a shared host's drift moves both alike), and prints each scenario's wall time
beside it, as a ratio.
``--model NAME`` sends the form field ``model`` (a model of the served folder); ``--compare-model
NAME`` asks the same server with that model too, each request alternating with the first model's,
and prints the ratio.

    .venv/bin/python benchmarks/predict_bench.py [--baseline HEAD~3] [--model-dir service/models] [--real DIR] \
        [--model fast --compare-model default]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from model_export.localiser.evaluate import masked_files  # noqa: E402
from service.core.machine import cpu_description  # noqa: E402
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


def run(client: httpx.Client, stacks: list[tuple[Path, Path]], repeats: int = 3, masks: bool = True,
        **form: str) -> tuple[float, dict]:
    files = [("stacks", (p.name, p.read_bytes())) for p, _ in stacks]
    files += [("masks", (m.name, m.read_bytes())) for _, m in stacks] if masks else []
    best, timing = float("inf"), {}
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = client.post("/v1/predict", files=files, data={"mc_samples": "100", **form})
        wall = time.perf_counter() - t0
        r.raise_for_status()
        if wall < best:
            best, timing = wall, r.json()["timing_ms"]
    return best, timing


SCENARIOS = (("A: 3 x 128x128x35", 1.0), ("B: 6 x 320x320x22", 2.0))


@contextmanager
def served(root: Path, model_dir: Path) -> Iterator[tuple[subprocess.Popen, int]]:
    """A server of the code under ``root`` serving ``model_dir``, on a free port, with a job store of
    its own (not the user's ``~/.svrnet``, which a running server of theirs owns), stopped and its
    store removed afterwards."""
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="svrnet-bench-") as store:
        env = dict(os.environ, SVRNET_PORT=str(port), SVRNET_MODELS_DIR=str(model_dir), SVRNET_LOG_LEVEL="warning",
                   PYTHONPATH=str(root), SVRNET_DATA_DIR=store)
        server = subprocess.Popen([sys.executable, "-c", "from service.main import run; run()"], env=env, cwd=root)
        try:
            yield server, port
        finally:
            server.terminate()
            server.wait(10)


@contextmanager
def revision_tree(rev: str) -> Iterator[Path]:
    """A git worktree of revision ``rev`` (its code and its shipped models), removed afterwards."""
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "baseline"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), rev],
                       check=True, capture_output=True)
        try:
            yield tree
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False)


def wait_ready(client: httpx.Client) -> None:
    for _ in range(300):
        try:
            if client.get("/readyz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise RuntimeError("the server did not become ready")


def measure(trees: list[tuple[Path, Path]], scenarios: list[list[tuple[Path, Path]]],
            real: list[tuple[Path, Path]] | None = None, models: tuple[str | None, ...] = (None,)) -> tuple[dict, float]:
    """Best-of-3 wall time and server stage timings per (scenario, image_consistency), the real scan's
    with and without masks (every stage on), and the first server's peak RSS. One server per
    ``(code root, models folder)`` of ``trees``, all started at once, and per model of ``models``
    (None: the server's default; the servers after the first: their default): every request goes to
    each server and model in turn, so that a machine whose speed drifts (a shared host) moves them
    alike. Keyed ``(tree index, model, ...)``."""
    out: dict = {}
    sides = [(0, model) for model in models] + [(i, None) for i in range(1, len(trees))]   # others: their default

    def best(clients: list[httpx.Client], key: tuple, stacks: list[tuple[Path, Path]], **form: object) -> None:
        for i, model in sides:
            wall, timing = run(clients[i], stacks, repeats=1, **form, **({"model": model} if model else {}))
            if (i, model, *key) not in out or wall < out[i, model, *key][0]:
                out[i, model, *key] = (wall, timing)

    with ExitStack() as stack:
        servers = [stack.enter_context(served(root, model_dir)) for root, model_dir in trees]
        clients = [stack.enter_context(httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=300))
                   for _, port in servers]
        for client in clients:
            wait_ready(client)
        for (name, _), stacks in zip(SCENARIOS, scenarios):
            for _ in range(3):                          # the two settings alternate: a drifting machine moves both
                for image in ("true", "false"):
                    best(clients, (name, image), stacks, image_consistency=image)
        if real:
            for _ in range(3):
                for masks in (True, False, True):       # masks twice a round: the best of six against three
                    best(clients, ("real", masks), real, masks=masks, masks_hold_csf="true" if masks else "false")
        return out, peak_rss_mb(servers[0][0].pid)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model-dir", default=str(ROOT / "service" / "models"))
    ap.add_argument("--baseline", help="a git revision to compare with, in the same run")
    ap.add_argument("--real", type=Path, help="a real scan's folder: NAME.nii.gz and NAME_brain_mask.nii.gz")
    ap.add_argument("--model", help="the model asked for (the form field `model`; default: the server's default)")
    ap.add_argument("--compare-model", help="a second model asked of the same server, alternating, as a ratio")
    args = ap.parse_args()
    print(f"machine: {cpu_description()}")
    real = [(stack, mask) for _, stack, mask in masked_files(args.real)] if args.real else None
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "b").mkdir()
        scenarios = [make_stacks(Path(tmp), 3, 128, 35, 1.1), make_stacks(Path(tmp) / "b", 6, 320, 22, 0.55)]
        print(f"source: {brain()[3]}")
        models = (args.model, args.compare_model) if args.compare_model else (args.model,)
        with ExitStack() as trees:
            served_trees = [(ROOT, Path(args.model_dir))]
            if args.baseline and not args.compare_model:
                tree = trees.enter_context(revision_tree(args.baseline))
                served_trees.append((tree, tree / "service" / "models"))
            both, rss = measure(served_trees, scenarios, real, models)
        now = {k[2:]: v for k, v in both.items() if k[:2] == (0, args.model)}
        before, against = None, f"revision {args.baseline}"
        if args.compare_model:
            before, against = {k[2:]: v for k, v in both.items() if k[:2] == (0, args.compare_model)}, \
                f"model {args.compare_model}"
        elif args.baseline:
            before = {k[2:]: v for k, v in both.items() if k[:2] == (1, None)}
        if args.model:
            print(f"model: {args.model}")
    for name, target in SCENARIOS:
        for image in ("true", "false"):
            wall, t = now[name, image]
            total = max(t["total"], 1e-9)
            ratio = f"; {before[name, image][0]:.2f} s with {against}: x{wall / before[name, image][0]:.2f}" \
                if before else ""
            print(f"{name}, image_consistency={image}: {wall:.2f} s wall over HTTP (target <= {target:.0f} s){ratio}")
            print("   server stages, ms (share of the server's total): "
                  + ", ".join(f"{k} {v:.0f} ({v / total:.0%})" for k, v in t.items() if k != "total")
                  + f"; total {t['total']:.0f}")
        print(f"   image consistency costs x{now[name, 'true'][0] / now[name, 'false'][0]:.2f} of the request without it")
    if real:
        for masks in (True, False):
            wall, t = now["real", masks]
            ratio = f"; {before['real', masks][0]:.2f} s with {against}: x{wall / before['real', masks][0]:.2f}" \
                if before else ""
            print(f"R: {len(real)} real stacks ({args.real.name}) {'with their manual masks' if masks else 'without masks'}: "
                  f"{wall:.2f} s wall over HTTP{ratio}")
            print("   server stages, ms: " + ", ".join(f"{k} {v:.0f}" for k, v in t.items()))
        print(f"   without masks x{now['real', False][0] / now['real', True][0]:.2f} the time with them "
              "(targets: <= 2 s with masks, <= 1.3 x without)")
    print(f"peak RSS of the server: {rss:.0f} MB (target <= 2048 MB)")
    print("localisation and N4 are summed over the stacks prepared in parallel; preprocess is the wall time of "
          "preparing them all")


if __name__ == "__main__":
    main()
