"""MC-dropout throughput of an exported model in onnxruntime.

Prints slices/s for one deterministic pass, for MC-100 as exported (trunk once, head x100) and for
the naive MC-100 (the whole network run 100 times: measured on a subset), and their ratios, all in
this one run.

    .venv/bin/python benchmarks/mc_bench.py [service/models/default/model.onnx]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from service.core.machine import cpu_description
from service.inference.model_file import load_model

DEFAULT = Path(__file__).resolve().parents[1] / "service" / "models" / "default" / "model.onnx"


def rate(fn, n_slices: int, repeats: int = 3) -> float:
    fn()  # warm-up
    best = min(_timed(fn) for _ in range(repeats))
    return n_slices / best


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main(path: Path = DEFAULT, n_slices: int = 128, batch: int = 64, mc: int = 100) -> None:
    print(f"machine: {cpu_description()}")
    model = load_model(path)
    size = model.info.input_size
    x = (np.random.default_rng(0).random((n_slices, 1, size, size)) * 255).astype(np.float32)
    det, ones = np.zeros(1, np.float32), np.ones(mc, np.float32)

    def batched(passes: np.ndarray, xs: np.ndarray) -> None:
        for i in range(0, len(xs), batch):
            model.run(xs[i:i + batch], passes)

    sub = x[:8]
    r_det = rate(lambda: batched(det, x), n_slices)
    r_mc = rate(lambda: batched(ones, x), n_slices)
    r_naive = rate(lambda: [batched(np.ones(1, np.float32), sub) for _ in range(mc)], len(sub), repeats=1)
    print(f"model {path.name}: {model.info.backbone}, {size}x{size} px, {n_slices} slices, batches of {batch}")
    print(f"  deterministic (1 pass)           {r_det:9.1f} slices/s")
    print(f"  MC-{mc} (trunk once, head x{mc})  {r_mc:9.1f} slices/s   {r_mc / r_det:.2f}x deterministic (target >= 0.85)")
    print(f"  naive MC-{mc} (network x{mc})     {r_naive:9.1f} slices/s   exported MC is {r_mc / r_naive:.0f}x faster")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT)
