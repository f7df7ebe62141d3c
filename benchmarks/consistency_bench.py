"""Cost of the stack-consistency stage: 6 stacks x 22 slices (the real-size predict case) and 3 x 40.

Prints milliseconds per 100 slices (target <= 50) and the share of the stage in a predict of the
same slices' statistics. Run: ``.venv/bin/python benchmarks/consistency_bench.py``.
"""

from __future__ import annotations

import time

import numpy as np

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.consistency import fit_stack  # noqa: E402
from tests.consistency.test_stack_fit import fake_network, stack  # noqa: E402


def best_of(fn, repeat: int = 5) -> float:  # noqa: ANN001
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    rng = np.random.default_rng(0)
    for n_stacks, n_slices in ((6, 22), (3, 40), (3, 80)):
        cases = []
        for _ in range(n_stacks):
            truth, nk = stack(rng, "moderate", n=n_slices)
            poses, _ = fake_network(truth, rng)
            cases.append((poses, nk, np.full(n_slices, 14.0)))
        t = best_of(lambda: [fit_stack(p, nk, noise_mm=noise) for p, nk, noise in cases])
        total = n_stacks * n_slices
        print(f"{n_stacks} stacks x {n_slices} slices: {t * 1e3:7.1f} ms in all, "
              f"{t * 1e3 * 100 / total:5.1f} ms per 100 slices (target <= 50)")


if __name__ == "__main__":
    main()
