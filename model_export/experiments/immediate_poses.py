"""The stream's immediate poses against the simulated truth: how far off they are, and whether their
``expected_error_mm`` says so.

Acquisitions of the validation volumes (``model_export.acquisitions``: three orthogonal stacks of
128 x 128 slices, masks sent) go slice by slice, in their acquisition order, through a
:class:`~service.streaming.session.StreamSession` in this process, the stack stage run after every
slice as the server runs it (:meth:`~service.streaming.session.StreamSession.firm_up`). Every
``pose`` answer with at least 50 brain pixels is scored the moment it is given: its E.D. against
the truth and twin-min, the RMS E.D. over the RMS expected error, and the accept flags, for the
slices answered before their stack decided its branch and after (docs/realtime.md).

    .venv/bin/python model_export/experiments/immediate_poses.py [--per-level 5] [--seed 13]
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np
from numpy.typing import NDArray

from model_export.acquisitions import SimulatedStack, simulate_acquisition
from model_export.atlas import load_volumes, validation_volumes
from service.geometry import anchors, twin
from service.geometry.pose import translate
from service.inference.estimator import OnnxPoseEstimator
from service.inference.model_file import load_model
from service.core.settings import DEFAULT_MODELS_DIR
from service.streaming.frames import SliceFrame
from service.streaming.session import StreamSession

LEVELS = ("mild", "moderate", "jumps")
MIN_BRAIN_PIXELS = 50


def network_frame(stack: SimulatedStack, k: int) -> NDArray[np.float64]:
    """Sent voxel -> a frame at the slice's brain centroid, mm (poses compared there, as E.D. is)."""
    idx = np.argwhere(stack.mask.array[:, :, k] > 0)
    c = idx.mean(0) if len(idx) else (np.array(stack.mask.array.shape[:2]) - 1) / 2.0
    sp = np.linalg.norm(stack.volume.affine[:3, :3], axis=0)
    return translate([c[0], c[1], 0.0]) @ np.diag([1 / sp[0], 1 / sp[1], 1 / sp[2], 1.0])


def ed(a: NDArray, b: NDArray, frame: NDArray, plane_x: float, twin_min: bool = False) -> float:
    """E.D. of two ``atlas_from_voxel`` poses of one sent slice, compared in ``frame``."""
    pa, pb = np.asarray(a) @ frame, np.asarray(b) @ frame
    return float(twin.twin_min_ed(pa, pb, plane_x) if twin_min else anchors.ed(pa, pb))


def immediate_rows(session: StreamSession, stacks: list[SimulatedStack], plane_x: float) -> list[dict]:
    """Stream ``stacks`` through ``session``; one row per immediate answer with brain."""
    rows = []
    for s in stacks:
        for k in (int(k) for k in np.argsort(s.times)):
            fit = session.fits.get(s.orientation)
            decided = bool(fit is not None and fit.fit is not None and fit.fit.branch_decided)
            frame = SliceFrame(s.orientation, k, s.volume.array[:, :, k], s.volume.affine @ translate([0, 0, k]),
                               s.mask.array[:, :, k] > 0)
            a = session.add_slice(frame)
            session.firm_up(s.orientation)
            if int((s.mask.array[:, :, k] > 0).sum()) < MIN_BRAIN_PIXELS:
                continue
            p = a.prediction
            pose = p.poses.poses[a.row] @ p.network_from_voxel[a.row]
            truth, at = s.atlas_from_voxel[k] @ translate([0, 0, k]), network_frame(s, k)
            rows.append({"decided": decided, "ed": ed(pose, truth, at, plane_x),
                         "ed_twin": ed(pose, truth, at, plane_x, True),
                         "expected": float(p.poses.expected_error_mm[a.row]), "accepted": p.reasons[a.row] is None})
        session.end_stack(s.orientation)
    return rows


def summary(rows: list[dict]) -> str:
    """One table cell: count, mean E.D. (truth / twin-min), RMS E.D. / RMS expected error."""
    if not rows:
        return "-"
    e, t, x = (np.array([r[f] for r in rows]) for f in ("ed", "ed_twin", "expected"))
    return f"{len(rows)}: {e.mean():.1f} / {t.mean():.1f} mm, {np.sqrt(np.mean(e ** 2) / np.mean(x ** 2)):.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-level", type=int, default=5)
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--model", default=str(DEFAULT_MODELS_DIR / "default" / "model.onnx"))
    args = ap.parse_args()
    model = load_model(args.model)
    estimator, plane = OnnxPoseEstimator(model), model.info.symmetry_plane_x_mm
    volumes = load_volumes(validation_volumes(model.info.metadata))
    rng = np.random.default_rng(args.seed)
    by_level: dict[str, list[dict]] = defaultdict(list)
    for n, level in enumerate(LEVELS):
        for i in range(args.per_level):
            vol = volumes[(i + n) % len(volumes)]
            stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level)
            by_level[level] += immediate_rows(StreamSession(estimator, None), stacks, plane)
    print("| motion | every answer: slices, mean E.D. (truth / twin-min), RMS E.D. / RMS expected | before the "
          "stack's branch | after | accepted: E.D. < 5 mm / > 10 mm |")
    print("|---|---|---|---|---|")
    for level, rows in by_level.items():
        ed_ = np.array([r["ed"] for r in rows])
        acc = np.array([r["accepted"] for r in rows])
        good, bad = acc[ed_ < 5], acc[ed_ > 10]
        print(f"| {level} | {summary(rows)} | {summary([r for r in rows if not r['decided']])} "
              f"| {summary([r for r in rows if r['decided']])} | {good.mean() if good.size else 0:.0%} of {good.size} / "
              f"{bad.mean() if bad.size else 0:.0%} of {bad.size} |")


if __name__ == "__main__":
    main()
