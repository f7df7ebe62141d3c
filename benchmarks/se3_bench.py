"""Fréchet mean + geodesic variance of 150 slices x 100 MC samples (the size of a typical request).

Prints the time per call, slices per second, and the speed-up over a per-slice loop of the same
code (the vectorisation ratio), all measured in this run.

    .venv/bin/python benchmarks/se3_bench.py
"""

from __future__ import annotations

import time

import numpy as np

from service.core.machine import cpu_description
from service.geometry import se3
from service.geometry.pose import make_pose


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(n_slices: int = 150, n_samples: int = 100) -> None:
    print(f"machine: {cpu_description()}")
    rng = np.random.default_rng(0)
    centre = se3.exp(np.concatenate([rng.normal(size=(n_slices, 1, 3)), rng.normal(scale=30, size=(n_slices, 1, 3))], -1))
    noise = make_pose(se3.so3_exp(rng.normal(scale=0.05, size=(n_slices, n_samples, 3))),
                      rng.normal(scale=2.0, size=(n_slices, n_samples, 3)))
    poses = centre @ noise
    batched = best_of(lambda: se3.frechet_mean_and_variance(poses), 7)
    looped = best_of(lambda: [se3.frechet_mean_and_variance(p) for p in poses[:30]], 2) * n_slices / 30
    print(f"Fréchet mean + variance, {n_slices} slices x {n_samples} samples")
    print(f"  batched: {batched * 1e3:7.1f} ms per call  ({n_slices / batched:8.0f} slices/s)  target <= 50 ms")
    print(f"  per-slice loop (extrapolated from 30): {looped * 1e3:7.1f} ms  -> batched is {looped / batched:.1f}x faster")


if __name__ == "__main__":
    main()
