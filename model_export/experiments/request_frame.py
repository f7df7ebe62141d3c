"""Does a request's common error grow with the network's error on its slices?

Every slice of a request shares one error that no stage sees: its common frame ``F``
(:func:`model_export.experiments.frame_bias.common_frame`, the Fréchet mean of ``P_k T_k^-1`` about
the brain's centre). Per request this prints its network error ``sigma`` (the slice-weighted RMS of
its stacks' ``network_error_mm``, :func:`service.consistency.frame_error.request_network_error_mm`),
the part of its RMS E.D. that ``F`` holds (``sqrt(RMS E.D.^2 - RMS E.D.^2 with F undone)``), the RMS
E.D. with ``F`` undone, and RMS E.D. over RMS expected error; then per source the medians, the
common part's RMS and its median ratio to ``sigma``, and over all requests the correlation of the
two. Sources: simulated 3-stack acquisitions of the validation volumes at ``--levels`` (masks
given, every stage on) and ``--scenes`` whole-uterus requests of three stacks planned about the
head at mild motion (:func:`~model_export.localiser.pose_accuracy.validation_cases`), each sent
with the atlas's brain masks and without masks.

    .venv/bin/python model_export/experiments/request_frame.py [--levels mild,moderate,jumps,independent] \\
        [--per-volume 1] [--scenes 10] [--seed 78] [--scene-seed 2000000]
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from model_export.acquisitions import simulate_acquisition  # noqa: E402
from model_export.atlas import DEFAULT_ATLAS_ROOT, VALIDATION_VOLUMES, load_volumes  # noqa: E402
from model_export.evaluate_acquisitions import run_acquisition  # noqa: E402
from model_export.experiments.frame_bias import common_frame  # noqa: E402
from model_export.localiser.pose_accuracy import pose_estimator  # noqa: E402
from model_export.localiser.pose_accuracy import score_scene, validation_cases  # noqa: E402
from service.geometry import anchors, twin  # noqa: E402
from service.pipeline.documents import stack_objects  # noqa: E402
from service.preprocess.localise import default_localiser  # noqa: E402


def request_row(final: NDArray, truth: NDArray, expected: NDArray, sigma: float) -> tuple[float, ...]:
    """``(sigma, common part, RMS E.D. with F undone, RMS E.D. / RMS expected)`` of one request's
    posed slices ``final`` against ``truth`` ``[n, 4, 4]`` (slice -> atlas mm)."""
    _, left = common_frame(final, truth, truth[:, :3, 3].mean(0))
    ed = anchors.ed(final, truth)
    told = np.isfinite(expected)
    ratio = float(np.sqrt(np.mean(ed[told] ** 2) / np.mean(expected[told] ** 2))) if told.any() else np.nan
    return sigma, float(np.sqrt(max(np.mean(ed ** 2) - np.mean(left ** 2), 0.0))), float(np.sqrt(np.mean(left ** 2))), ratio


def acquisition_rows(levels: list[str], per_volume: int, seed: int) -> dict[str, list]:
    estimator = pose_estimator()
    plane = estimator.info.symmetry_plane_x_mm
    rng, rows = np.random.default_rng(seed), defaultdict(list)
    for level in levels:
        for vol in load_volumes(VALIDATION_VOLUMES, DEFAULT_ATLAS_ROOT) * per_volume:
            stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level)
            predictions, prepared, truth = run_acquisition(stacks, estimator)
            finals, trues, expected = [], [], []
            for res, p, true in zip(stack_objects(predictions[0]), prepared, truth):
                final = p.in_network_frame([s["atlas_from_voxel"] for s in res["slices"]])
                posed = np.array([s["reason"] != "empty" for s in res["slices"]])
                finals.append(final[posed])
                trues.append(twin.nearer(final, true, plane)[posed])
                expected.append(np.array([np.nan if s["expected_error_mm"] is None else s["expected_error_mm"]
                                          for s in res["slices"]])[posed])
            rows[level].append(request_row(np.concatenate(finals), np.concatenate(trues), np.concatenate(expected),
                                           predictions[0][0].request_network_error_mm))
    return rows


def scene_rows(count: int, seed: int) -> dict[str, list]:
    estimator, localiser, rows = pose_estimator(), default_localiser(), defaultdict(list)
    for case in validation_cases(count, seed, 3, motion="mild", planning="orthogonal"):
        for variant in ("brain", "localiser"):
            got = score_scene(case, variant, estimator, localiser if variant == "localiser" else None)
            posed = np.isfinite(got["ed"])
            rows[f"scenes, {'no mask' if variant == 'localiser' else 'brain mask'}"].append(request_row(
                got["poses"][posed], got["truth"][posed], got["expected"][posed], float(got["network_error"])))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--levels", default="mild,moderate,jumps,independent")
    ap.add_argument("--per-volume", type=int, default=1)
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=78)
    ap.add_argument("--scene-seed", type=int, default=2_000_000)
    args = ap.parse_args()
    rows = {**acquisition_rows([x for x in args.levels.split(",") if x], args.per_volume, args.seed),
            **(scene_rows(args.scenes, args.scene_seed) if args.scenes else {})}
    print("| requests | count | network error (median) | common part (RMS) | its median ratio to the network error "
          "| RMS E.D. with the common frame undone | RMS E.D. / RMS expected (median) |")
    print("|---|---|---|---|---|---|---|")
    every = []
    for source, values in rows.items():
        v = np.array(values, np.float64)
        every.append(v)
        print(f"| {source} | {len(v)} | {np.nanmedian(v[:, 0]):.1f} mm | {np.sqrt(np.mean(v[:, 1] ** 2)):.2f} mm "
              f"| {np.nanmedian(v[:, 1] / v[:, 0]):.2f} | {np.sqrt(np.mean(v[:, 2] ** 2)):.2f} mm | {np.nanmedian(v[:, 3]):.2f} |")
    v = np.concatenate(every)
    ok = np.isfinite(v[:, 0])
    print(f"\nover {int(ok.sum())} requests: correlation of the network error and the common part "
          f"{np.corrcoef(v[ok, 0], v[ok, 1])[0, 1]:.2f}")


if __name__ == "__main__":
    main()
