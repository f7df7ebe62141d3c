"""Cost of the stack-consistency stage: 6 stacks x 22 slices (the real-size predict case), 3 x 40 and 3 x 80.

Prints milliseconds per 100 slices (the stage's share of a request; the targets are whole
requests', ``predict_bench.py``) and, as a ratio that holds on a loaded machine too, the stage's
time over that of the twin-aware MC-100 statistics of the same slices; then the
cost of weighing the error's shape (a model's ``mc_error_shape``: each tilt and the in-plane
translation its lever arm couples form one block of twice the slices,
:mod:`service.consistency.motion_blocks`) over weighing every coordinate alike. Run:
``.venv/bin/python benchmarks/consistency_bench.py``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.core.settings import Settings  # noqa: E402
from service.core.threads import limit_blas_threads  # noqa: E402
from service.consistency import fit_stack  # noqa: E402
from service.core.machine import cpu_description  # noqa: E402
from service.geometry import anchors, se3  # noqa: E402
from service.inference.estimator import statistics  # noqa: E402
from benchmarks.timing import alternated  # noqa: E402
from tests.consistency.test_stack_fit import fake_network, stack  # noqa: E402


SHAPE = np.array([3.84, 0.53, 0.18, 0.03, 0.13, 1.30]) / 1.0016      # a model's measured shape, mean 1


def measure(n_stacks: int, n_slices: int, repeats: int = 5, seed: int = 0) -> dict[str, float]:
    """Seconds of the stage over ``n_stacks`` simulated stacks of ``n_slices`` slices (moderate motion,
    best of ``repeats``), with the error's shape weighed, and of the MC-100 statistics of the same
    slices, the three timed alternately (:func:`~benchmarks.timing.alternated`)."""
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(n_stacks):
        truth, nk = stack(rng, "moderate", n=n_slices)
        poses, _ = fake_network(truth, rng)
        cases.append((poses, nk, np.full(n_slices, 14.0)))
    mc = anchors.encode(np.concatenate([p for p, _, _ in cases])[:, None]
                        @ se3.exp(rng.normal(0, 0.05, (n_stacks * n_slices, 100, 6))))
    return alternated({"stage": lambda: [fit_stack(p, nk, expected_error_mm=e) for p, nk, e in cases],
                       "shaped": lambda: [fit_stack(p, nk, expected_error_mm=e, error_shape=SHAPE) for p, nk, e in cases],
                       "statistics": lambda: statistics(mc, "anchor")}, repeats, warm=False)


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    limit_blas_threads(Settings().blas_threads)              # as the server and the job workers run
    print(f"machine: {cpu_description()}")
    for n_stacks, n_slices in ((6, 22), (3, 40), (3, 80)):
        m = measure(n_stacks, n_slices)
        t, total = m["stage"], n_stacks * n_slices
        print(f"{n_stacks} stacks x {n_slices} slices: {t * 1e3:7.1f} ms in all, "
              f"{t * 1e3 * 100 / total:5.1f} ms per 100 slices; "
              f"{t / m['statistics']:4.2f}x the MC-100 statistics of the same slices ({m['statistics'] * 1e3:.1f} ms); "
              f"with the error's shape {m['shaped'] / t:4.2f}x that")


if __name__ == "__main__":
    main()
