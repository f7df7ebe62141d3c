"""Pose accuracy without masks, against the truth: whole-uterus scenes whose slice poses are known.

Real scans have no true slice poses, and poses with manual masks are no truth either: the pose
network learnt the atlas's own brain masks, and a manual mask (everything inside the skull) is
another definition. This benchmark generates held-out whole-uterus scenes around the validation
atlas brains (:func:`~model_export.localiser.scenes.synth_scene`, ``heldout`` style, T2-like
contrast, the head at the atlas's size so that its slice poses are rigid) and runs each stack alone
through ``/v1/predict``'s pipeline with three masks:

* ``brain``: the atlas's brain mask carried along (what the pose network was trained with);
* ``skull``: everything inside the skull (how manual masks are drawn, what the localiser learns);
* ``localiser``: none uploaded; the service's localiser finds it;
* ``skull-csf+G`` (``--variants``): the ``skull`` mask grown by ``G`` mm and sent with
  ``masks_hold_csf``, as a manual mask drawn to the skull's outer edge would be.

Every slice with brain in the truth is scored against its true pose (E.D., mm) and twin-min (the
nearer of the truth and its left-right twin); a slice the answer calls ``empty`` is counted apart.

    .venv/bin/python -m model_export.localiser.pose_accuracy --scenes 10 [--variants skull,skull-csf+0,skull-csf+3,localiser]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from numpy.typing import NDArray

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split
from model_export.localiser.scenes import HeadModel, Scene, synth_scene
from service.pipeline.documents import stack_objects
from service.geometry import anchors, twin
from service.io.volume import Volume
from service.pipeline.predict import predict
from service.pipeline.prepare import PreparedStack, StackUpload, prepare_stacks
from service.preprocess.localisation import grown
from service.preprocess.localise import Localiser

VARIANTS = ("brain", "skull", "localiser")
MIN_BRAIN_PIXELS = 200
"""Slices with less true brain than this are not scored (the brain's caps: no pose network sees them well)."""


def validation_scenes(count: int, seed: int = 2_000_000, root=DEFAULT_ATLAS_ROOT) -> list[Scene]:  # noqa: ANN001
    """``count`` rigid held-out scenes of T2-like contrast, the validation volumes in turn."""
    heads = [HeadModel.from_arrays(v.image, v.mask, v.affine) for v in load_volumes(split(root)[1], root)]
    return [synth_scene(heads[i % len(heads)], np.random.default_rng(seed + i), "heldout", random_contrast=False,
                        rigid=True) for i in range(count)]


def _upload(scene: Scene, variant: str) -> StackUpload:
    if variant.startswith("skull-csf+"):
        mask = grown(scene.mask, scene.volume.spacing, float(variant[len("skull-csf+"):]))
        return StackUpload(f"scene-{variant}.nii.gz", scene.volume, Volume(mask.astype(np.uint8), scene.volume.affine),
                           mask_holds_csf=True)
    mask = {"brain": scene.brain, "skull": scene.mask, "localiser": None}[variant]
    return StackUpload(f"scene-{variant}.nii.gz", scene.volume,
                       None if mask is None else Volume(mask.astype(np.uint8), scene.volume.affine))


def slice_poses(answer: dict, prepared: PreparedStack) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """A stack's answer (one ``stacks[]`` object of ``/v1/predict``) as slice poses ``[n, 4, 4]``
    (slice frame -> atlas mm, the frame E.D. and the twin are defined in) and which slices it posed
    (not ``empty``)."""
    voxel_from_slice = np.linalg.inv(prepared.slices.slice_from_voxel)
    poses = np.array([s["atlas_from_voxel"] for s in answer["slices"]], np.float64) @ voxel_from_slice
    return poses, np.array([s["reason"] != "empty" for s in answer["slices"]])


def score_scene(scene: Scene, variant: str, estimator, localiser: Localiser | None = None,  # noqa: ANN001
                mc_samples: int = 100) -> dict[str, NDArray]:
    """Per scored slice of one scene and mask variant: E.D. and twin-min E.D. (NaN where ``empty``).
    An estimator with a ``truth`` attribute (a stand-in for the network) is told each slice's true
    network-frame pose first, as :func:`model_export.evaluate_acquisitions.run_acquisition` does."""
    info = estimator.info
    prepared = prepare_stacks([_upload(scene, variant)], info, True, workers=1, localiser=localiser)
    if hasattr(estimator, "truth"):
        estimator.truth = prepared[0].in_network_frame(scene.atlas_from_voxel)
    predictions, _ = predict(prepared, estimator, mc_samples, info.variance_threshold)
    answer = stack_objects(predictions)[0]
    poses, posed = slice_poses(answer, prepared[0])
    truth = scene.atlas_from_voxel @ np.linalg.inv(prepared[0].slices.slice_from_voxel)
    scored = np.flatnonzero(scene.brain.sum(axis=(0, 1)) >= MIN_BRAIN_PIXELS)
    keep = scored[posed[scored]]
    plane = float(getattr(info, "symmetry_plane_x_mm", twin.DEFAULT_PLANE_X_MM))
    ed, ed_min = np.full(len(scored), np.nan), np.full(len(scored), np.nan)
    ed[posed[scored]] = anchors.ed(poses[keep], truth[keep])
    ed_min[posed[scored]] = twin.twin_min_ed(poses[keep], truth[keep], plane)
    expected = np.array([np.nan if a["expected_error_mm"] is None else a["expected_error_mm"]
                         for a in answer["slices"]], np.float64)[scored]
    accepted = np.array([bool(a["accepted"]) for a in answer["slices"]])[scored]
    return {"ed": ed, "ed_min": ed_min, "expected": expected, "accepted": accepted}


def pose_accuracy(scenes: list[Scene], estimator, localiser: Localiser,  # noqa: ANN001
                  variants: tuple[str, ...] = VARIANTS, mc_samples: int = 100) -> dict[str, dict]:
    """Per mask variant over all ``scenes``: median and mean E.D. and twin-min E.D. of the posed brain
    slices, their count, the share of brain slices left ``empty``, RMS E.D. over RMS
    ``expected_error_mm`` (1: the expected errors are honest), and the slices accepted, of which
    how many lie over 10 mm from the truth."""
    keys = ("ed", "ed_min", "expected", "accepted")
    rows: dict[str, dict[str, list]] = {v: {key: [] for key in keys} for v in variants}
    for scene in scenes:
        for variant in variants:
            got = score_scene(scene, variant, estimator, localiser if variant == "localiser" else None, mc_samples)
            for key in keys:
                rows[variant][key].append(got[key])
    out = {}
    for variant, r in rows.items():
        ed, ed_min = np.concatenate(r["ed"]), np.concatenate(r["ed_min"])
        expected, accepted = np.concatenate(r["expected"]), np.concatenate(r["accepted"])
        posed = np.isfinite(ed)
        told = posed & np.isfinite(expected)
        out[variant] = {"median_ed_mm": float(np.median(ed[posed])) if posed.any() else None,
                        "mean_ed_mm": float(np.mean(ed[posed])) if posed.any() else None,
                        "median_twin_min_mm": float(np.median(ed_min[posed])) if posed.any() else None,
                        "mean_twin_min_mm": float(np.mean(ed_min[posed])) if posed.any() else None,
                        "slices": int(posed.sum()), "empty_share": float(1 - posed.mean()) if len(ed) else None,
                        "rms_ed_over_rms_expected": float(np.sqrt(np.mean(ed[told] ** 2) / np.mean(expected[told] ** 2)))
                        if told.any() else None,
                        "accepted": int((accepted & posed).sum()),
                        "accepted_over_10mm": int((accepted & posed & (np.nan_to_num(ed, nan=0.0) > 10.0)).sum())}
    return out


def main() -> None:
    from model_export.localiser.evaluate import _pose_estimator
    from service.core.settings import DEFAULT_LOCALISERS_DIR

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=2_000_000)
    ap.add_argument("--localiser", default=str(DEFAULT_LOCALISERS_DIR / "default" / "model.onnx"))
    ap.add_argument("--variants", default=",".join(VARIANTS))
    args = ap.parse_args()
    result = pose_accuracy(validation_scenes(args.scenes, args.seed), _pose_estimator(), Localiser.load(args.localiser),
                           tuple(args.variants.split(",")))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
