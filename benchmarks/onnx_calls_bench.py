"""The service's networks run as one call over every core against calls side by side, one core each.

For the shipped pose model (a request of ``--slices`` slices: every test-time view at MC-100, as
``/v1/predict`` runs it) and the shipped localiser (a 320 x 320 x 22 stack of 1.125 mm pixels, its
mirrored pass included), each way is timed ``--repeats`` times, alternating, in one process; it prints
the medians, the best times and their ratio, and checks that both ways give the same numbers.

* **one call over every core**: a session of ``os.cpu_count()`` intra-op threads, its calls one after
  the other (the pose model's batches of 64 rows, the localiser's of 8 slices);
* **side by side** (:class:`~service.core.onnx.SideBySide`, as the service runs them): a session of
  one intra-op thread, called from one thread per core.

    .venv/bin/python benchmarks/onnx_calls_bench.py [--slices 105] [--repeats 8]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import onnxruntime as ort

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import service.preprocess.localise as localise  # noqa: E402
from service.core.machine import cpu_description  # noqa: E402
from service.core.onnx import SideBySide, session_options  # noqa: E402
from service.core.settings import DEFAULT_LOCALISERS_DIR, DEFAULT_MODELS_DIR  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402
from service.io.volume import Volume  # noqa: E402
from service.preprocess.localiser_inputs import localiser_inputs  # noqa: E402


def one_call_each(session_path: Path) -> tuple[ort.InferenceSession, SideBySide]:
    """A session over every core whose calls run one after the other."""
    return ort.InferenceSession(str(session_path), session_options(0), providers=["CPUExecutionProvider"]), SideBySide(1)


def compare(name: str, ways: dict[str, object], repeats: int) -> None:
    """Time each of ``ways`` (callables) ``repeats`` times, alternating; print medians and the ratio."""
    outs = {k: f() for k, f in ways.items()}
    first, second = outs.values()
    same = float(np.abs(np.asarray(first) - np.asarray(second)).max())
    times: dict[str, list[float]] = {k: [] for k in ways}
    for _ in range(repeats):
        for k, f in ways.items():
            t = time.perf_counter()
            f()
            times[k].append((time.perf_counter() - t) * 1e3)
    (a, ta), (b, tb) = times.items()
    print(f"{name}: {a} {np.median(ta):.0f} ms (best {min(ta):.0f}), {b} {np.median(tb):.0f} ms (best {min(tb):.0f}): "
          f"x{np.median(tb) / np.median(ta):.2f} (best x{min(tb) / min(ta):.2f}); largest difference {same:.2g}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--slices", type=int, default=105)
    ap.add_argument("--repeats", type=int, default=8)
    args = ap.parse_args()
    print(f"machine: {cpu_description()}")

    path = DEFAULT_MODELS_DIR / "default" / "model.onnx"
    side = OnnxPoseEstimator(load_model(path))
    session, serial = one_call_each(path)
    one = OnnxPoseEstimator(replace(side.model, session=session, calls=serial))
    size = side.info.input_size
    x = np.random.default_rng(0).random((args.slices, size, size), np.float32) * 255
    compare(f"pose model, {args.slices} slices, MC-100, {side.info.tta_views} views",
            {"one call over every core": lambda: one.sample_labels(x, 100),
             "side by side": lambda: side.sample_labels(x, 100)}, args.repeats)

    loc_path = DEFAULT_LOCALISERS_DIR / "default" / "model.onnx"
    loc = localise.Localiser.load(loc_path)
    session, serial = one_call_each(loc_path)
    whole = replace(loc, session=session, calls=serial)
    stack = Volume(np.random.default_rng(1).random((320, 320, 22), np.float32) * 300, np.diag([1.125, 1.125, 3.3, 1.0]))
    inputs, _ = localiser_inputs(stack, loc.grid_mm)
    name = loc.session.get_inputs()[0].name
    batch = localise.BATCH_SLICES

    def whole_stack() -> np.ndarray:
        localise.BATCH_SLICES = 8                          # the batch a call over every core runs best with
        try:
            return whole._logits(name, inputs)
        finally:
            localise.BATCH_SLICES = batch

    compare("localiser, 320 x 320 x 22, mirrored pass",
            {"one call over every core": whole_stack, "side by side": lambda: loc._logits(name, inputs)}, args.repeats)


if __name__ == "__main__":
    main()
