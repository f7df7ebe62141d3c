"""Where the stack model puts a streamed slice before its pose is computed, against the truth: the
stack's mean placement (what the stream's immediate poses use) against the motion model's pose at
the stack's latest received slices.

The acquisitions and the session are those of ``immediate_poses.py`` (the stack stage after every
slice). After each fit that decided the stack's branch, every later slice with brain, until the
next fit, is predicted by: ``placement`` (the stack's placement), ``latest`` (the fitted
``atlas_from_scanner`` of the latest slice received), ``latest3`` (the mean of the latest three),
``shrunk`` (``latest`` drawn toward the placement by the motion kernel's correlation over the slices
since the fit); ``previous_truth`` is the true ``atlas_from_scanner`` of the previous slice received
(an oracle: how far the fetus moved in one slice). Printed per level: the mean / median E.D. of each
against the truth, of the network's own answer (twin-min) and of the answer the stream gave.

    .venv/bin/python model_export/experiments/immediate_predictors.py [--per-level 5] [--seed 13]
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parent))

from immediate_poses import LEVELS, MIN_BRAIN_PIXELS, ed, network_frame  # noqa: E402
from model_export.acquisitions import simulate_acquisition  # noqa: E402
from model_export.atlas import load_volumes, validation_volumes  # noqa: E402
from service.consistency.motion_model import from_coordinates, to_coordinates  # noqa: E402
from service.core.settings import DEFAULT_MODELS_DIR  # noqa: E402
from service.geometry.pose import translate  # noqa: E402
from service.inference.estimator import OnnxPoseEstimator  # noqa: E402
from service.inference.model_file import load_model  # noqa: E402
from service.streaming.frames import SliceFrame  # noqa: E402
from service.streaming.session import StreamSession  # noqa: E402


def predictors(session: StreamSession, stack: str) -> Callable[[int], dict[str, NDArray]] | None:
    """Each predictor's ``atlas_from_scanner`` after the stack's latest fit, as a function of the
    slices received since (None: no fit, or its branch undecided)."""
    fit = session.fits.get(stack)
    if fit is None or fit.fit is None or not fit.fit.branch_decided or fit.fit.atlas_from_scanner is None:
        return None
    states = [session.slices[stack][k] for k in sorted(session.slices[stack])]
    index = [s.frame.index for s in states]
    fitted = fit.poses @ np.stack([s.network_from_voxel[0] @ np.linalg.inv(s.frame.scanner_from_voxel) for s in states])
    latest = [index.index(k) for k in session.stacks[stack].arrival_order() if k in index][-3:]
    placement, centre, length = fit.fit.atlas_from_scanner, fit.fit.centre, fit.fit.bandwidth
    y = to_coordinates(fitted[latest], placement, centre)

    def at(since: int) -> dict[str, NDArray]:
        rho = float(np.exp(-0.5 * (since / length) ** 2)) if np.isfinite(length) else 0.0
        return {"placement": placement, "latest": fitted[latest[-1]],
                "latest3": from_coordinates(y.mean(0, keepdims=True), placement, centre)[0],
                "shrunk": from_coordinates(y[-1:] * rho, placement, centre)[0]}
    return at


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-level", type=int, default=5)
    ap.add_argument("--seed", type=int, default=13)
    args = ap.parse_args()
    model = load_model(str(DEFAULT_MODELS_DIR / "default" / "model.onnx"))
    estimator, plane = OnnxPoseEstimator(model), model.info.symmetry_plane_x_mm
    volumes = load_volumes(validation_volumes(model.info.metadata))
    rng = np.random.default_rng(args.seed)
    rows: dict[str, list[dict[str, float]]] = defaultdict(list)
    for n, level in enumerate(LEVELS):
        for i in range(args.per_level):
            vol = volumes[(i + n) % len(volumes)]
            session = StreamSession(estimator, None)
            for s in simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level):
                predict, since, previous = None, 0, None
                for k in (int(k) for k in np.argsort(s.times)):
                    sfv = s.volume.affine @ translate([0, 0, k])
                    frame = SliceFrame(s.orientation, k, s.volume.array[:, :, k], sfv, s.mask.array[:, :, k] > 0)
                    a = session.add_slice(frame)
                    since += 1
                    truth, at = s.atlas_from_voxel[k] @ translate([0, 0, k]), network_frame(s, k)
                    if predict is not None and int((s.mask.array[:, :, k] > 0).sum()) >= MIN_BRAIN_PIXELS:
                        p = a.prediction
                        row = {name: ed(A @ sfv, truth, at, plane) for name, A in predict(since).items()}
                        row["previous_truth"] = ed(previous @ sfv, truth, at, plane)
                        row["network (twin-min)"] = ed(p.estimate.mean[a.row] @ p.network_from_voxel[a.row], truth, at,
                                                       plane, True)
                        row["answered"] = ed(p.poses.poses[a.row] @ p.network_from_voxel[a.row], truth, at, plane)
                        rows[level].append(row)
                    previous = truth @ np.linalg.inv(sfv)
                    fitted = session.firmed.get(s.orientation, 0)
                    session.firm_up(s.orientation)
                    if session.firmed.get(s.orientation, 0) != fitted:
                        predict, since = predictors(session, s.orientation), 0
                session.end_stack(s.orientation)
    names = list(next(iter(rows.values()))[0])
    print("| motion | slices | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for level, rs in rows.items():
        cells = [f"{np.mean([r[m] for r in rs]):.1f} / {np.median([r[m] for r in rs]):.1f}" for m in names]
        print(f"| {level} | {len(rs)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
