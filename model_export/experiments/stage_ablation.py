"""What limits the stack-consistency stage? The same acquisitions, the network's poses edited by an oracle.

The network is run once per simulated acquisition (the validation volumes, the seed of
``svrnet-train evaluate --acquisitions``). Its per-slice errors are then edited with the truth
before the stage sees them, one hypothesis per row, and each row goes through the server's
``predict`` (the stage, the pooling) and is scored as the evaluation scores it (mean E.D. over
slices with >= 20 mask pixels, against the truth and twin-min):

* ``network``: as the model gave them (the evaluation's figure);
* ``oracle weights``: each slice's expected error is its true twin-min error (is the MC spread
  the limit, as weights?);
* ``errors shuffled``: each slice keeps the error of another slice of its stack (same
  distribution, no correlation between neighbours; its spread travels with it);
* ``tails cut at X mm``: a slice whose error exceeds X mm gets the error of a random slice of
  its stack below X (are the outer planes' large errors the limit?);
* ``errors x F``: every error scaled by F on the SE(3) log (how accurate must the network be?);
* ``exact acquisition order``: the network's poses as given, the stage told each stack's true
  order (is choosing the order the limit?).

Below the table, the network's own errors by depth: ``|Tz - middle| / half-extent`` of each slice
against the brain's true extent along its normal (training planes reach 0.94 of it).

An error is ``E = N^-1 M`` (network frame), ``M`` the network's pose and ``N`` the truth or its
twin, whichever is nearer; an edited pose is ``N' E'`` with ``N'`` on the branch the network chose.

    .venv/bin/python model_export/experiments/stage_ablation.py [--level moderate] [--per-volume 2]   # needs ../shared/data

With ``--cache`` name the ``--model`` that made the cached outputs: its ``mc_error_scale`` turns
their spreads into the stage's expected errors (another model's scale moves the figures by up to
tenths of a mm).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import pickle
import sys
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import simulate_acquisition  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split  # noqa: E402
from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, Scored, run_acquisition, score  # noqa: E402
from service.consistency.slice_order import SliceOrder  # noqa: E402
from service.geometry import se3, twin  # noqa: E402
from service.geometry.anchors import ed  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator, PoseEstimate  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402
from service.pipeline.predict import predict  # noqa: E402


class Recording:
    """The ONNX estimator, keeping its last estimate."""

    def __init__(self, estimator: OnnxPoseEstimator) -> None:
        self.estimator, self.info, self.last = estimator, estimator.info, None

    def estimate(self, inputs: np.ndarray, mc_samples: int) -> PoseEstimate:
        self.last = self.estimator.estimate(inputs, mc_samples)
        return self.last


class Fixed:
    """An estimator that answers with one given estimate."""

    def __init__(self, info, est: PoseEstimate) -> None:  # noqa: ANN001
        self.info, self.est = info, est

    def estimate(self, inputs: np.ndarray, mc_samples: int) -> PoseEstimate:
        return self.est


def shuffled(size: np.ndarray, stack: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Whose error each slice takes: a permutation within each stack's slices in the brain (``stack`` -1: not scored)."""
    out = np.arange(len(size))
    for s in np.unique(stack[stack >= 0]):
        idx = np.flatnonzero(stack == s)
        out[idx] = rng.permutation(idx)
    return out


def tails_cut(limit: float) -> Callable:
    """Whose error each slice takes: its own, or where over ``limit`` mm a random one of its stack's under it."""
    def pick(size: np.ndarray, stack: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        out = np.arange(len(size))
        for s in np.unique(stack[stack >= 0]):
            idx = np.flatnonzero(stack == s)
            good = idx[size[idx] <= limit]
            bad = idx[size[idx] > limit]
            if len(good):
                out[bad] = rng.choice(good, len(bad))
        return out
    return pick


def edited(est: PoseEstimate, truth: np.ndarray, stack: np.ndarray, plane: float, scale_mc: float, rng: np.random.Generator,
           pick: Callable | None = None, factor: float = 1.0, oracle_weights: bool = False) -> PoseEstimate:
    """The estimate with its errors moved (``pick``: whose error each slice takes), scaled, or its spread the truth."""
    near = twin.nearer(est.mean, truth, plane)
    err = se3.inverse(near) @ est.mean                                      # network-frame errors
    size = ed(est.mean, near)
    src = np.arange(len(err)) if pick is None else pick(size, stack, rng)
    xi = se3.log(err[src]) * factor
    mean = near @ se3.exp(xi)
    spread = est.spread_mm[src] * factor
    if oracle_weights:
        spread = np.maximum(twin.twin_min_ed(mean, truth, plane), 0.5) / scale_mc
    return dataclasses.replace(est, mean=mean, spread_mm=spread)


def exact_orders(stacks: list) -> list[SliceOrder]:
    """Each stack's true acquisition order, as a request would give it (slice indices in time order)."""
    return [SliceOrder.parse(",".join(str(int(k)) for k in np.argsort(s.times, kind="stable"))) for s in stacks]


DEPTH_BANDS = ((0.0, 0.35), (0.35, 0.7), (0.7, 0.85), (0.85, 0.94), (0.94, np.inf))


def acquisitions(onnx: Recording, volumes: list, level: str, per_volume: int, seed: int,
                 cache: Path | None) -> list[tuple]:
    """``(stacks, prepared, truth, estimate)`` of each simulated acquisition (``per_volume`` of each of
    ``volumes``), from ``cache`` where it exists."""
    if cache is not None and cache.exists():
        with cache.open("rb") as f:
            return pickle.load(f)
    rng, out = np.random.default_rng(seed), []
    for vol in volumes:
        for _ in range(per_volume):
            stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level)
            _, prepared, truth = run_acquisition(stacks, onnx)
            out.append((stacks, prepared, truth, onnx.last))
    if cache is not None:
        with cache.open("wb") as f:
            pickle.dump(out, f)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=Path("service/models/default/model.onnx"))
    ap.add_argument("--level", default="moderate")
    ap.add_argument("--per-volume", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cache", type=Path, help="keep the acquisitions and the network's estimates here (a pickle), "
                                               "to compare versions of the stage on the same network poses")
    ap.add_argument("--rows", nargs="*", help="only these rows")
    args = ap.parse_args()
    onnx = Recording(OnnxPoseEstimator(load_model(args.model)))
    info, plane = onnx.info, onnx.info.symmetry_plane_x_mm
    scale_mc = getattr(info, "mc_error_scale", 1.0)
    edit = functools.partial(edited, plane=plane, scale_mc=scale_mc)
    same = lambda e, t, s, r: e  # noqa: E731
    rows: dict[str, Callable] = {
        "network": same,
        "oracle weights": lambda e, t, s, r: edit(e, t, s, rng=r, oracle_weights=True),
        "errors shuffled within stacks": lambda e, t, s, r: edit(e, t, s, rng=r, pick=shuffled),
        "errors x 0 (the truth)": lambda e, t, s, r: edit(e, t, s, rng=r, factor=0.0),
        "tails cut at 20 mm": lambda e, t, s, r: edit(e, t, s, rng=r, pick=tails_cut(20.0)),
        "tails cut at 10 mm": lambda e, t, s, r: edit(e, t, s, rng=r, pick=tails_cut(10.0)),
        "errors x 0.75": lambda e, t, s, r: edit(e, t, s, rng=r, factor=0.75),
        "errors x 0.5": lambda e, t, s, r: edit(e, t, s, rng=r, factor=0.5),
        "errors x 0.5, oracle weights": lambda e, t, s, r: edit(e, t, s, rng=r, factor=0.5, oracle_weights=True),
        "exact acquisition order": same,
    }
    told = {"exact acquisition order": exact_orders}       # rows whose stage is told the stacks' orders
    rows = {k: v for k, v in rows.items() if not args.rows or k in args.rows}
    scored = {k: Scored() for k in rows}
    edit_rng = np.random.default_rng(args.seed + 1000)
    volumes = load_volumes(split(DEFAULT_ATLAS_ROOT)[1], DEFAULT_ATLAS_ROOT)
    depth, network_min = [], []
    for i, (stacks, prepared, truth, est) in enumerate(acquisitions(onnx, volumes, args.level, args.per_volume,
                                                                    args.seed, args.cache)):
        truth_all = np.concatenate(truth)
        inside = np.concatenate([p.prepared.mask_pixels for p in prepared]) >= MIN_MASK_PIXELS
        depth.append(volumes[i // args.per_volume].relative_depth(truth_all)[inside])
        network_min.append(twin.twin_min_ed(est.mean, truth_all, plane)[inside])
        # slices outside the brain keep their own errors (they are not scored)
        stack = np.concatenate([np.where(p.prepared.mask_pixels >= MIN_MASK_PIXELS, i, -1)
                                for i, p in enumerate(prepared)])
        for name, row in rows.items():
            orders = told[name](stacks) if name in told else None
            res = predict(prepared, Fixed(info, row(est, truth_all, stack, edit_rng)), 100,
                          info.variance_threshold, orders=orders)[0]
            score(res, prepared, truth, stacks, plane, scored[name])
    print(f"{args.level} motion, the validation volumes x {args.per_volume} acquisitions; mean E.D. (mm) over "
          f"slices with >= {MIN_MASK_PIXELS} mask pixels")
    print("| the network's poses | network twin-min | after the stage | after the stage, twin-min | p90 |")
    print("|---|---|---|---|---|")
    for name, sc in scored.items():
        keep = sc.array("mask_pixels") >= MIN_MASK_PIXELS
        e, m = sc.array("ed")[keep], sc.array("ed_min")[keep]
        print(f"| {name} | {sc.array('ed_network_min')[keep].mean():.1f} | {e.mean():.2f} | {m.mean():.2f} | "
              f"{np.percentile(e, 90):.1f} |")
    depth, network_min = np.concatenate(depth), np.concatenate(network_min)
    print("\nThe network's own twin-min E.D. by depth (|Tz - middle| / half-extent of the brain along the normal):")
    print("| depth | slices | network twin-min (mm) | share of the summed error |")
    print("|---|---|---|---|")
    for lo, hi in DEPTH_BANDS:
        m = (depth >= lo) & (depth < hi)
        print(f"| {lo:.2f}-{hi:.2f} | {100 * m.mean():.1f} % | {network_min[m].mean() if m.any() else np.nan:.1f} | "
              f"{100 * network_min[m].sum() / network_min.sum():.1f} % |")


if __name__ == "__main__":
    main()
