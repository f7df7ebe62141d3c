"""Fréchet mean + geodesic variance of 150 slices x 100 MC samples (the size of a typical request).

Prints the time per call, slices per second, and the speed-up over a per-slice loop of the same
code (the vectorisation ratio), the two timed alternately in this run (:mod:`benchmarks.timing`).

    .venv/bin/python benchmarks/se3_bench.py
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.timing import alternated  # noqa: E402
from service.core.machine import cpu_description  # noqa: E402
from service.geometry import se3  # noqa: E402
from service.geometry.pose import make_pose  # noqa: E402


def main(n_slices: int = 150, n_samples: int = 100) -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    print(f"machine: {cpu_description()}")
    rng = np.random.default_rng(0)
    centre = se3.exp(np.concatenate([rng.normal(size=(n_slices, 1, 3)), rng.normal(scale=30, size=(n_slices, 1, 3))], -1))
    noise = make_pose(se3.so3_exp(rng.normal(scale=0.05, size=(n_slices, n_samples, 3))),
                      rng.normal(scale=2.0, size=(n_slices, n_samples, 3)))
    poses = centre @ noise
    times = alternated({"batched": lambda: se3.frechet_mean_and_variance(poses),
                        "looped": lambda: [se3.frechet_mean_and_variance(p) for p in poses[:30]]}, repeats=3)
    batched, looped = times["batched"], times["looped"] * n_slices / 30
    print(f"Fréchet mean + variance, {n_slices} slices x {n_samples} samples")
    print(f"  batched: {batched * 1e3:7.1f} ms per call  ({n_slices / batched:8.0f} slices/s)  target <= 50 ms")
    print(f"  per-slice loop (extrapolated from 30): {looped * 1e3:7.1f} ms  -> batched is {looped / batched:.1f}x faster")


if __name__ == "__main__":
    main()
