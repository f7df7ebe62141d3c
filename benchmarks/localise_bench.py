"""The brain localiser: its time per stack, and what it costs ``/v1/predict`` against uploaded masks.

1. :meth:`Localiser.localise` on stacks of the sizes scanners write (random content in a field of
   view that ends in air, as a whole-uterus stack's does: the cost does not depend on the content),
   split into input, network (both passes) and geometry; and the same stack cropped through the
   body on two sides (the network then also sees the fluid band beyond them: a larger grid). Then
   the network's time with its calls two at a time on half the cores each (as the service runs
   it) against one call at a time on all of them, and the pose network's alike.
2. The predict pipeline (no HTTP; BLAS threads limited as the server limits them; N4, 100 MC
   samples, every stage on) on the same stacks with the reference masks and without them: wall
   times, their ratio, and the median E.D. between the two sets of poses. Stacks: the real scan of
   ``../shared/data/real_scans/mial_lausanne_t30`` where it is, else generated whole-uterus stacks
   around a phantom brain.

3. With ``--baseline DIR``: :meth:`Localiser.localise` of the 320 x 320 x 22 stack by the localiser
   against another localiser's folder (a model about to ship against the shipped one), alternating
   in one process, and the largest difference of their probabilities.

    .venv/bin/python benchmarks/localise_bench.py [--localiser DIR] [--baseline DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from model_export.localiser.evaluate import REAL_SCANS, masked_files, pose_agreement  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from service.core.machine import cpu_description  # noqa: E402
from service.core.settings import DEFAULT_LOCALISERS_DIR, Settings  # noqa: E402
from service.core.threads import limit_blas_threads  # noqa: E402
from service.pipeline.prepare import StackUpload  # noqa: E402
from service.io.volume import Volume, read_volume  # noqa: E402
from service.preprocess.brain_shape import brain_from_probabilities  # noqa: E402
from service.preprocess.localise import Localiser  # noqa: E402
from service.preprocess.localiser_inputs import localiser_inputs  # noqa: E402

SIZES = [((320, 320, 22), 1.125, 3.3), ((256, 256, 40), 1.17, 3.0), ((512, 512, 30), 0.7, 4.0), ((192, 192, 25), 1.6, 3.0)]


def timed(fn, repeats: int = 5) -> tuple[float, object]:  # noqa: ANN001
    out = fn()
    t = time.perf_counter()
    for _ in range(repeats):
        out = fn()
    return (time.perf_counter() - t) / repeats * 1e3, out


def random_stack(shape: tuple[int, int, int], pixel: float, thick: float, rng: np.random.Generator,
                 cut: bool = False) -> Volume:
    """Random content in a field of view that ends in 10 mm of air (``cut``: cut through the body on
    two sides, as a stack cropped to the uterus is)."""
    content = rng.random(shape, np.float32) * 300
    air = int(round(10 / pixel))
    content[:air], content[-air:], content[:, :air], content[:, -air:] = 0, 0, 0, 0
    if cut:
        content = np.ascontiguousarray(content[air:, air:])
    return Volume(content, np.diag([pixel, pixel, thick, 1.0]))


def stage_times(loc: Localiser) -> None:
    print(f"{'stack':>18} {'pixel':>6} {'inputs ms':>10} {'network ms':>11} {'geometry ms':>12} {'total ms':>9}")
    rng = np.random.default_rng(0)
    rows = [(shape, pixel, thick, "") for shape, pixel, thick in SIZES] + [(SIZES[0][0], *SIZES[0][1:], "cut")]
    for shape, pixel, thick, cut in rows:
        vol = random_stack(shape, pixel, thick, rng, cut=bool(cut))
        t_in, (x, grid) = timed(lambda: localiser_inputs(vol, loc.grid_mm))
        name = loc.session.get_inputs()[0].name
        t_net, logits = timed(lambda: loc._logits(name, x))
        prob = 1 / (1 + np.exp(-logits))
        t_geo, _ = timed(lambda: brain_from_probabilities(prob, loc.grid_mm ** 2 * thick / 1e3, loc.grid_mm))
        t_all, _ = timed(lambda: loc.localise(vol))
        label = "x".join(map(str, vol.array.shape)) + (" cut" if cut else "")
        print(f"{label:>18} {pixel:>6.2f} {t_in:>10.0f} {t_net:>11.0f} {t_geo:>12.0f} {t_all:>9.0f}")


def side_by_side_ratios(loc: Localiser) -> None:
    """The localiser's and the pose network's time, calls two at a time against one at a time on
    every core, alternating in one process."""
    from service.inference.estimator import OnnxPoseEstimator
    from service.inference.model_file import load_model
    from service.core.threads import available_cores

    cores = available_cores()
    vol = Volume(np.random.default_rng(1).random(SIZES[0][0], np.float32) * 300, np.diag([1.125, 1.125, 3.3, 1.0]))
    x, _ = localiser_inputs(vol, loc.grid_mm)
    name = loc.session.get_inputs()[0].name
    one_call = Localiser.load(loc.path, threads=cores)
    pose_path = ROOT / "service" / "models" / "default" / "model.onnx"
    poses = {side: OnnxPoseEstimator(load_model(pose_path, threads=0 if side else cores)) for side in (True, False)}
    size = poses[True].info.input_size
    slices = np.random.default_rng(2).uniform(0, 255, (105, size, size)).astype(np.float32)
    rows = [("localiser, 320x320x22, both passes", lambda: loc._logits(name, x), lambda: one_call._logits(name, x)),
            ("pose network, 105 slices, MC-100", lambda: poses[True].sample_labels(slices, 100),
             lambda: poses[False].sample_labels(slices, 100))]
    print(f"\n{'network':>36} {'two calls at a time ms':>23} {'one call ms':>12} {'ratio':>6}")
    for label, side, one in rows:
        times = {0: [], 1: []}
        for _ in range(5):                                            # alternating: the same machine state
            times[0].append(timed(side, 1)[0])
            times[1].append(timed(one, 1)[0])
        a, b = float(np.median(times[0])), float(np.median(times[1]))
        print(f"{label:>36} {a:>23.0f} {b:>12.0f} {a / b:>6.2f}")


def baseline_ratio(loc: Localiser, baseline: Localiser, repeats: int = 9) -> None:
    """A stack's :meth:`Localiser.localise` by ``loc`` and by ``baseline``, alternating (the same machine
    state for both), and how far apart their probabilities lie."""
    vol = random_stack(*SIZES[0], np.random.default_rng(1))
    times: dict[str, list[float]] = {"loc": [], "base": []}
    for _ in range(repeats):
        times["loc"].append(timed(lambda: loc.localise(vol), 1)[0])
        times["base"].append(timed(lambda: baseline.localise(vol), 1)[0])
    a, b = (float(np.median(times[k])) for k in ("loc", "base"))
    apart = float(np.abs(loc.probabilities(vol)[0] - baseline.probabilities(vol)[0]).max())
    print(f"\nlocalise, 320x320x22 ({repeats} alternating runs, median): {loc.path.parent.name} {loc.version} "
          f"{a:.0f} ms, {baseline.path.parent.name} {baseline.version} {b:.0f} ms: ratio {a / b:.2f} "
          f"(best {min(times['loc']):.0f} / {min(times['base']):.0f} ms); probabilities at most {apart:.1e} apart")


def uploads() -> tuple[list[StackUpload], str]:
    real = REAL_SCANS / "mial_lausanne_t30"
    if real.is_dir():
        return [StackUpload(name, read_volume(stack), read_volume(mask)) for name, stack, mask in masked_files(real)], \
            "real scan mial_lausanne_t30, manual masks"
    from model_export.localiser.scenes import HeadModel, synth_stack
    from tests.support.phantoms import one_fetus_scene, phantom_brain

    head = HeadModel.from_arrays(*phantom_brain(11))
    out = []                                 # one request's stacks: their brains where one fetus's would be
    stacks = one_fetus_scene([synth_stack(head, np.random.default_rng(200 + seed), "heldout") for seed in range(3)])
    for seed, (vol, mask) in enumerate(stacks):
        out.append(StackUpload(f"generated{seed}", vol, Volume(mask.astype(np.uint8), vol.affine)))
    return out, "generated whole-uterus stacks (phantom brain), true masks"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--localiser", type=Path, default=DEFAULT_LOCALISERS_DIR / "default",
                    help="the localiser's folder (default: the shipped one)")
    ap.add_argument("--baseline", type=Path, help="another localiser's folder, timed against it")
    args = ap.parse_args()
    limit_blas_threads(Settings().blas_threads)              # as the server and the job workers run
    print(f"machine: {cpu_description()}")
    loc = Localiser.load(args.localiser / "model.onnx")
    print(f"localiser {loc.version}, grid {loc.grid_mm} mm, mirrored pass run by the service: {loc.mirrored}")
    stage_times(loc)
    side_by_side_ratios(loc)
    if args.baseline:
        baseline_ratio(loc, Localiser.load(args.baseline / "model.onnx"))
    stacks, what = uploads()
    print(f"\n/v1/predict pipeline on {what}:")
    r = pose_agreement(stacks, loc, pose_estimator())
    print(f"with masks {r['seconds_with_masks']:.2f} s, without {r['seconds_without']:.2f} s: "
          f"ratio {r['latency_ratio']:.2f}; poses without vs with masks: median E.D. {r['median_ed_mm']:.2f} mm "
          f"over {r['slices']} slices (two runs with masks: {r['repeat_median_ed_mm']:.2f} mm)")


if __name__ == "__main__":
    main()
