"""Slice-to-volume reconstruction: time per stage and accuracy against the ground-truth volume.

Three stacks of 35 slices of 128 x 128 (1.1 mm in-plane, 3.5 mm thick; Gaussian PSF of FWHM 3.5 mm
through-plane and 1.2 pixels in-plane; Rician noise at 2 % of the median brain intensity) at three
near-orthogonal orientations are cut from the atlas
``../shared/data/fetal_atlas/crl_sta/STA30_T2.nii.gz`` (else a phantom) with independent rigid
motion per slice; the reconstruction is a 0.8 mm volume. Scenarios:

  1. Gaussian average from the true poses;
  2. SVR (3 rounds) from the true poses;
  3. SVR from poses perturbed like a prediction (RMS 3 mm translation, RMS 3 deg rotation per slice,
     about each slice's centre);
  4. SVR from the poses the service predicts (``--model``, default the shipped
     ``service/models/default/model.onnx``; 100 MC passes, N4, the stacks' true masks), using only
     the slices it accepts -- exactly what a reconstruction job without uploaded poses does.

For each: seconds per stage and in total (target <= 60 s on a 2-core machine), PSNR and NCC
against the atlas resampled to the output grid inside the brain mask (after a global linear
intensity fit), and the mean pixel displacement of the final slice poses from the truth, also
after removing the common rigid offset of all slices (the mean error of the perturbation, which
the slices cannot reveal; the reconstruction keeps the frame of its input poses).

    .venv/bin/python benchmarks/recon_bench.py [--svr-iterations 3] [--resolution 0.8]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.geometry import sampling, se3  # noqa: E402
from service.geometry.pose import make_pose  # noqa: E402
from service.io.volume import Volume, read_volume  # noqa: E402
from service.reconstruction.pipeline import ReconstructionConfig, reconstruct  # noqa: E402
from service.reconstruction.registration import anchor_frame  # noqa: E402
from service.reconstruction.slices import SliceSet  # noqa: E402
from tests.phantoms import phantom_brain, stack_affine  # noqa: E402
from tests.reconstruction.helpers import thick_stack  # noqa: E402

ATLAS = ROOT.parent / "shared" / "data" / "fetal_atlas" / "crl_sta"


def brain() -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """(image, mask, affine, name): the STA30 atlas when the shared data are present, else a phantom."""
    if (ATLAS / "STA30_T2.nii.gz").exists() and (ATLAS / "STA30_mask.nii.gz").exists():
        img, msk = read_volume(ATLAS / "STA30_T2.nii.gz"), read_volume(ATLAS / "STA30_mask.nii.gz")
        return img.array.astype(np.float32), (msk.array > 0).astype(np.float32), img.affine, "atlas STA30"
    img, msk, aff = phantom_brain(0)
    return img, msk, aff, "phantom"


def rigid_about(centres: np.ndarray, rot_deg: np.ndarray, trans_mm: np.ndarray) -> np.ndarray:
    """``[n, 4, 4]``: rotate by rotation vectors (deg) about ``centres [n, 3]``, then translate."""
    rot = se3.so3_exp(np.deg2rad(rot_deg))
    t = centres + trans_mm - np.einsum("nij,nj->ni", rot, centres)
    return make_pose(rot, t)


def make_data(seed: int = 0):  # noqa: ANN201
    img, msk, aff, name = brain()
    rng = np.random.default_rng(seed)
    idx = np.argwhere(msk > 0)
    centre = aff[:3, :3] @ idx.mean(0) + aff[:3, 3]
    stacks, truth = [], []
    for i, axis in enumerate((2, 1, 0)):
        shape = [128, 128, 128]
        shape[axis] = 35
        rot = se3.so3_exp(rng.normal(scale=0.1, size=3))
        saff = stack_affine(axis, rot, 1.1, 3.5, tuple(shape), centre_mm=tuple(centre))
        motion = rigid_about(np.repeat(centre[None], 35, 0), rng.normal(scale=2.0, size=(35, 3)),
                             rng.normal(scale=1.5, size=(35, 3)))
        s, m = thick_stack(img, msk, aff, saff, tuple(shape), axis, motion)
        noise = 0.02 * float(np.percentile(img[msk > 0], 50))
        s = np.abs(s + rng.normal(scale=noise, size=s.shape) + 1j * rng.normal(scale=noise, size=s.shape))
        stacks.append((Volume(s.astype(np.float32), saff), m))
        truth.append(motion @ saff)
    return img, msk, aff, name, stacks, truth


def evaluate(result, img, msk, aff, frame: np.ndarray | None = None) -> tuple[float, float]:  # noqa: ANN001
    """PSNR (dB; peak = max of the truth in the mask) after a linear intensity fit, and NCC, in the brain mask.

    ``frame`` (``4 x 4``, truth atlas -> reconstruction frame): compare after undoing a common offset.
    """
    grid = result.grid
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in grid.shape], indexing="ij"), -1).reshape(-1, 3)
    pts = ijk @ grid.affine[:3, :3].T + grid.affine[:3, 3]
    ref = sampling.sample_points(img, aff, pts)
    inside = sampling.sample_points(msk, aff, pts) > 0.5
    vol = result.volume.array.reshape(-1)
    if frame is not None:
        vol = sampling.sample_points(result.volume.array, result.volume.affine, pts @ frame[:3, :3].T + frame[:3, 3])
    x = vol[inside].astype(np.float64)
    y = ref[inside].astype(np.float64)
    a, b = np.polyfit(x, y, 1)
    psnr = 10 * np.log10(y.max() ** 2 / np.mean((a * x + b - y) ** 2))
    return float(psnr), float(np.corrcoef(x, y)[0, 1])


def pose_error(ss: SliceSet, estimate: np.ndarray, truth: np.ndarray) -> float:
    """Mean distance (mm) between pixel positions under the estimated and the true poses."""
    return float(np.linalg.norm(ss.positions(estimate) - ss.positions(truth), axis=1).mean())


def common_offset(ss: SliceSet, estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The rigid ``4 x 4`` (truth atlas -> estimate frame) common to all slices (robust Kabsch fit)."""
    i = int(np.flatnonzero(ss.include)[0])
    return estimate[i] @ np.linalg.inv(anchor_frame(ss, truth, estimate)[i])


def relative_pose_error(ss: SliceSet, estimate: np.ndarray, truth: np.ndarray) -> float:
    """:func:`pose_error` after removing the common rigid offset of all slices."""
    return pose_error(ss, anchor_frame(ss, truth, estimate), truth)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--svr-iterations", type=int, default=3)
    ap.add_argument("--resolution", type=float, default=0.8)
    ap.add_argument("--perturb-mm", type=float, default=3.0, help="RMS translation error of scenario 3")
    ap.add_argument("--perturb-deg", type=float, default=3.0, help="RMS rotation error of scenario 3")
    ap.add_argument("--config", default="{}", help="ReconstructionConfig overrides, as a Python dict literal")
    ap.add_argument("--only", default="1234", help="scenarios to run")
    ap.add_argument("--model", type=Path, default=ROOT / "service" / "models" / "default" / "model.onnx")
    args = ap.parse_args()
    cfg = ReconstructionConfig(**eval(args.config, {}))  # noqa: S307 - a local benchmark option

    t0 = time.perf_counter()
    img, msk, aff, name, stacks, truth = make_data()
    include = [np.ones(len(t), bool) for t in truth]
    ss_true = SliceSet.from_stacks([(v, m, t, i) for (v, m), t, i in zip(stacks, truth, include)])
    t_all = np.concatenate(truth)
    print(f"data: {name}, 3 stacks x 35 slices of 128 x 128 (1.1 x 1.1 x 3.5 mm), "
          f"{ss_true.include.sum()} slices with brain, {ss_true.n_pixels} pixels; simulated in "
          f"{time.perf_counter() - t0:.1f} s")
    rng = np.random.default_rng(1)
    n = len(t_all)
    centres = ss_true.centres()
    noise = rigid_about(centres, rng.normal(scale=args.perturb_deg / np.sqrt(3), size=(n, 3)),
                        rng.normal(scale=args.perturb_mm / np.sqrt(3), size=(n, 3)))
    perturbed = noise @ t_all
    ss_pert = SliceSet.from_stacks([(v, m, p, i) for (v, m), p, i in
                                    zip(stacks, np.split(perturbed, np.cumsum([len(t) for t in truth])[:-1]), include)])
    scenarios = [("1", "Gaussian average, true poses", ss_true, 0),
                 ("2", f"SVR x{args.svr_iterations}, true poses", ss_true, args.svr_iterations),
                 ("3", f"SVR x{args.svr_iterations}, poses + {args.perturb_mm:g} mm / {args.perturb_deg:g} deg noise",
                  ss_pert, args.svr_iterations)]
    if "3" in args.only:
        print(f"scenario 3 starting pose error: {pose_error(ss_true, perturbed, t_all):.2f} mm "
              f"({relative_pose_error(ss_true, perturbed, t_all):.2f} mm without the common rigid offset, "
              "which no reconstruction can see and which is kept)")
    if "4" in args.only and args.model.exists():
        from service.inference.estimator import OnnxPoseEstimator
        from service.inference.model_file import load_model
        from service.inference.pipeline import StackUpload
        from service.jobs.worker import predicted_poses

        t1 = time.perf_counter()
        estimator = OnnxPoseEstimator(load_model(args.model, threads=2))
        uploads = [StackUpload(f"stack{i}", v, Volume(m.astype(np.float32), v.affine), f"mask{i}")
                   for i, (v, m) in enumerate(stacks)]
        poses, _ = predicted_poses(uploads, estimator)
        predicted = np.concatenate([p for p, _ in poses])
        accepted = np.concatenate([a for _, a in poses])
        ss_pred = SliceSet.from_stacks([(v, m, p, a) for (v, m), (p, a) in zip(stacks, poses)])
        print(f"scenario 4: predicted {len(predicted)} poses in {time.perf_counter() - t1:.1f} s, "
              f"{int(accepted.sum())} accepted; pose error {pose_error(ss_true, predicted, t_all):.2f} mm "
              f"(accepted only: {pose_error(ss_pred, predicted, t_all) if accepted.any() else float('nan'):.2f} mm)")
        if accepted.any():
            scenarios.append(("4", f"SVR x{args.svr_iterations}, poses predicted by {args.model.parent.name}",
                              ss_pred, args.svr_iterations))
        else:
            print("scenario 4: the model accepted no slice; nothing to reconstruct")
    rows = []
    for key, label, ss, its in scenarios:
        if key not in args.only:
            continue
        res = reconstruct(ss, resolution_mm=args.resolution, svr_iterations=its, config=cfg)
        psnr, ncc = evaluate(res, img, msk, aff)
        err = pose_error(ss_true, res.atlas_from_voxel_final, t_all)
        rel = relative_pose_error(ss_true, res.atlas_from_voxel_final, t_all)
        stages = ", ".join(f"{k} {v:.1f}s" for k, v in res.timings.items() if k != "total")
        print(f"[{key}] {label}: grid {res.volume.array.shape}, total {res.timings['total']:.1f} s ({stages})")
        print(f"     PSNR {psnr:.2f} dB, NCC {ncc:.4f}, pose error {err:.2f} mm "
              f"({rel:.2f} mm without the common rigid offset), "
              f"included {int(res.included.sum())}/{int(ss.include.sum())}")
        rows.append((label, psnr, ncc, err, rel, res.timings["total"]))
        if key == "3":
            ga = reconstruct(ss, resolution_mm=args.resolution, svr_iterations=0, config=cfg)
            p0, n0 = evaluate(ga, img, msk, aff)
            offset = common_offset(ss_true, res.atlas_from_voxel_final, t_all)
            pa, na = evaluate(res, img, msk, aff, frame=offset)
            angle = np.degrees(np.linalg.norm(se3.so3_log(offset[:3, :3])))
            shift = np.linalg.norm(ss_true.positions(offset @ t_all) - ss_true.positions(t_all), axis=1).mean()
            print(f"     common offset of the result {shift:.2f} mm / {angle:.2f} deg; undoing it: "
                  f"PSNR {pa:.2f} dB, NCC {na:.4f}")
            print(f"     Gaussian average of the perturbed poses: PSNR {p0:.2f} dB, NCC {n0:.4f}")
            rows.append(("Gaussian average, perturbed poses", p0, n0, pose_error(ss_true, perturbed, t_all),
                         relative_pose_error(ss_true, perturbed, t_all), ga.timings["total"]))
    print("\nsummary: scenario | PSNR dB | NCC | pose error mm | same without common offset | seconds")
    for label, psnr, ncc, err, rel, secs in rows:
        print(f"  {label:50s} {psnr:6.2f}  {ncc:.4f}  {err:5.2f}  {rel:5.2f}  {secs:5.1f}")


if __name__ == "__main__":
    main()
