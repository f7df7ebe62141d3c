"""MC-dropout throughput of an exported model in onnxruntime.

Prints slices/s for one deterministic pass, for MC-100 as exported (trunk once, head x100) and for
the naive MC-100 (the whole network run 100 times: measured on a subset), and their ratios, the
three timed alternately in this one run (:mod:`benchmarks.timing`).

    .venv/bin/python benchmarks/mc_bench.py [service/models/default/model.onnx]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.timing import alternated  # noqa: E402
from service.core.machine import cpu_description  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402

DEFAULT = Path(__file__).resolve().parents[1] / "service" / "models" / "default" / "model.onnx"


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
    times = alternated({"det": lambda: batched(det, x), "mc": lambda: batched(ones, x),
                        "naive": lambda: [batched(np.ones(1, np.float32), sub) for _ in range(mc)]})
    r_det, r_mc, r_naive = n_slices / times["det"], n_slices / times["mc"], len(sub) / times["naive"]
    print(f"model {path.name}: {model.info.backbone}, {size}x{size} px, {n_slices} slices, batches of {batch}")
    print(f"  deterministic (1 pass)           {r_det:9.1f} slices/s")
    print(f"  MC-{mc} (trunk once, head x{mc})  {r_mc:9.1f} slices/s   {r_mc / r_det:.2f}x deterministic (target >= 0.85)")
    print(f"  naive MC-{mc} (network x{mc})     {r_naive:9.1f} slices/s   exported MC is {r_mc / r_naive:.0f}x faster")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", nargs="?", type=Path, default=DEFAULT, help="an exported model (default: the shipped one)")
    main(ap.parse_args().model)
