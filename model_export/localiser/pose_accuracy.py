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
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from model_export.acquisitions import ORIENTATIONS, stack_axes
from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split
from model_export.localiser.scenes import HeadModel, Scene, synth_scene
from model_export.localiser.surroundings import random_rotation
from service.core.settings import DEFAULT_LOCALISERS_DIR, DEFAULT_MODELS_DIR
from service.geometry import anchors, twin
from service.inference.estimator import OnnxPoseEstimator
from service.inference.model_file import load_model
from service.pipeline.documents import stack_objects
from service.io.volume import Volume
from service.pipeline.predict import predict
from service.pipeline.prepare import PreparedStack, StackUpload, prepare_stacks
from service.preprocess.localisation import grown
from service.preprocess.localise import Localiser

VARIANTS = ("brain", "skull", "localiser")
PLANNINGS = ("independent", "orthogonal")
"""How a case's stacks lie about the head: each in an orientation of its own (``independent``: two
stacks can be near parallel), or ``orthogonal``: axial, coronal and sagittal to the head, each
tilted by about 10 deg (:func:`~model_export.acquisitions.stack_axes`), as a radiographer plans a
scan's stacks about the fetal brain and as the pose benchmarks' acquisitions lie."""
MIN_BRAIN_PIXELS = 200
"""Slices with less true brain than this are not scored (the brain's caps: no pose network sees them well)."""


def pose_estimator(model: Path | None = None) -> OnnxPoseEstimator:
    """The pose network the benchmarks measure with: ``model`` (an exported ONNX file) or the
    service's shipped ``default`` model."""
    return OnnxPoseEstimator(load_model(model or DEFAULT_MODELS_DIR / "default" / "model.onnx"))


def validation_scenes(count: int, seed: int = 2_000_000, root=DEFAULT_ATLAS_ROOT) -> list[Scene]:  # noqa: ANN001
    """``count`` rigid held-out scenes of T2-like contrast, the validation volumes in turn."""
    heads = [HeadModel.from_arrays(v.image, v.mask, v.affine) for v in load_volumes(split(root)[1], root)]
    return [synth_scene(heads[i % len(heads)], np.random.default_rng(seed + i), "heldout", random_contrast=False,
                        rigid=True) for i in range(count)]


def validation_cases(count: int, seed: int = 2_000_000, stacks: int = 1, root=DEFAULT_ATLAS_ROOT,  # noqa: ANN001
                     motion: str | None = None, planning: str = "independent") -> list[list[Scene]]:
    """``count`` held-out requests of ``stacks`` whole-uterus stacks each: one stack, as
    :func:`validation_scenes` draws it, or several of one head (the validation volumes in turn),
    each drawn in its own surroundings with the first's look (the scan's contrast, the head's CSF,
    skull and scalp), lying about the head as ``planning`` says (:data:`PLANNINGS`; the draws are
    made all the same), and placed in one scanner frame (:func:`in_one_frame`), as a scan's stacks
    of one fetus are sent together."""
    if planning not in PLANNINGS:
        raise ValueError(f"planning must be one of {PLANNINGS}")
    if stacks == 1 and motion is None and planning == "independent":
        return [[scene] for scene in validation_scenes(count, seed, root)]
    heads = [HeadModel.from_arrays(v.image, v.mask, v.affine) for v in load_volumes(split(root)[1], root)]
    planes = list(ORIENTATIONS)
    cases = []
    for i in range(count):
        rngs = [np.random.default_rng(seed + 1000 * i + k) for k in range(stacks + 1)]
        plan = rngs[stacks].spawn(1)[0]                       # the frame's draws untouched
        axes = [stack_axes(planes[(k if stacks > 1 else i) % len(planes)], plan).T if planning == "orthogonal"
                else None for k in range(stacks)]               # single stacks: the planes in turn
        scenes = [synth_scene(heads[i % len(heads)], rngs[0], "heldout", random_contrast=False, rigid=True,
                              motion=motion, orientation=axes[0])]
        scenes += [synth_scene(heads[i % len(heads)], rng, "heldout", random_contrast=False, rigid=True, motion=motion,
                               look=scenes[0].look, orientation=a) for rng, a in zip(rngs[1:stacks], axes[1:])]
        cases.append(in_one_frame(scenes, rngs[stacks]))
    return cases


def in_one_frame(scenes: list[Scene], rng: np.random.Generator) -> list[Scene]:
    """The stacks of one head given scanner affines that place the head alike in each: every stack's
    voxels map to the scanner through one drawn atlas -> scanner transform and its middle slice's
    true pose (the other slices' poses then differ from it by the head's motion, as a moving
    fetus's do). The slices' true atlas poses, the images and the masks stay as drawn.

    Example (two stacks' middle slices map through one frame):
        >>> from model_export.localiser.scenes import Scene
        >>> from service.io.volume import Volume
        >>> poses = [np.repeat(np.diag([1.0, 1.0, 3.0, 1.0])[None], 3, 0), np.repeat(np.eye(4)[None], 3, 0)]
        >>> out = in_one_frame([Scene(Volume(np.zeros((2, 2, 3)), np.eye(4)), None, None, p) for p in poses],
        ...                    np.random.default_rng(0))
        >>> bool(np.allclose(out[0].volume.affine @ np.diag([1, 1, 1 / 3, 1]), out[1].volume.affine))
        True
    """
    scanner_from_atlas = np.eye(4)
    scanner_from_atlas[:3, :3] = random_rotation(rng)
    scanner_from_atlas[:3, 3] = rng.uniform(-60.0, 60.0, 3)
    out = []
    for scene in scenes:
        middle = scene.atlas_from_voxel[len(scene.atlas_from_voxel) // 2]
        out.append(replace(scene, volume=replace(scene.volume, affine=scanner_from_atlas @ middle)))
    return out


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


def score_scene(scene: Scene | list[Scene], variant: str, estimator, localiser: Localiser | None = None,  # noqa: ANN001
                mc_samples: int = 100) -> dict[str, NDArray]:
    """Per scored slice of one request (a scene, or a case's stacks sent together) and mask variant:
    E.D. and twin-min E.D. (NaN where ``empty``), the answer's poses (``poses``, slice -> atlas mm;
    NaN where ``empty``) and the true ones (``truth``), the stacks' scored slices one after the
    other; and the request's
    network error (``network_error``, :mod:`service.consistency.frame_error`). An estimator with a
    ``truth`` attribute (a stand-in for the network) is told each slice's true network-frame pose
    first, as :func:`model_export.evaluate_acquisitions.run_acquisition` does."""
    scenes = scene if isinstance(scene, list) else [scene]
    info = estimator.info
    prepared = prepare_stacks([_upload(s, variant) for s in scenes], info, True, workers=1, localiser=localiser)
    if hasattr(estimator, "truth"):
        estimator.truth = np.concatenate([p.in_network_frame(s.atlas_from_voxel) for p, s in zip(prepared, scenes)])
    predictions, _ = predict(prepared, estimator, mc_samples, info.variance_threshold)
    plane = float(getattr(info, "symmetry_plane_x_mm", twin.DEFAULT_PLANE_X_MM))
    rows: dict[str, list] = {"ed": [], "ed_min": [], "expected": [], "accepted": [], "poses": [], "truth": []}
    for one, answer, stack in zip(scenes, stack_objects(predictions), prepared):
        poses, posed = slice_poses(answer, stack)
        truth = one.atlas_from_voxel @ np.linalg.inv(stack.slices.slice_from_voxel)
        scored = np.flatnonzero(one.brain.sum(axis=(0, 1)) >= MIN_BRAIN_PIXELS)
        keep = scored[posed[scored]]
        ed, ed_min = np.full(len(scored), np.nan), np.full(len(scored), np.nan)
        ed[posed[scored]] = anchors.ed(poses[keep], truth[keep])
        ed_min[posed[scored]] = twin.twin_min_ed(poses[keep], truth[keep], plane)
        shown = np.where(posed[:, None, None], poses, np.nan)[scored]
        expected = np.array([np.nan if a["expected_error_mm"] is None else a["expected_error_mm"]
                             for a in answer["slices"]], np.float64)[scored]
        accepted = np.array([bool(a["accepted"]) for a in answer["slices"]])[scored]
        for key, value in zip(rows, (ed, ed_min, expected, accepted, shown, truth[scored])):
            rows[key].append(value)
    return {**{key: np.concatenate(value) for key, value in rows.items()},
            "network_error": np.array(predictions[0].request_network_error_mm if predictions else np.nan)}


def pose_accuracy(scenes: list[Scene] | list[list[Scene]], estimator, localiser: Localiser,  # noqa: ANN001
                  variants: tuple[str, ...] = VARIANTS, mc_samples: int = 100) -> dict[str, dict]:
    """Per mask variant over all ``scenes`` (each a request: one scene, or a case's stacks): median and
    mean E.D. and twin-min E.D. of the posed brain slices, their count, the share of brain slices
    left ``empty``, RMS E.D. over RMS ``expected_error_mm`` (1: the expected errors are honest), and
    the slices accepted, of which how many lie over 10 mm from the truth. ``gap_to_<variant>``: the
    median E.D. between the ``localiser`` answer's slices and that variant's where both posed them
    (issue 27's measure between poses without and with masks, here with a truth to read it by)."""
    keys = ("ed", "ed_min", "expected", "accepted", "poses")
    rows: dict[str, dict[str, list]] = {v: {key: [] for key in keys} for v in variants}
    for scene in scenes:
        for variant in variants:
            got = score_scene(scene, variant, estimator, localiser if variant == "localiser" else None, mc_samples)
            for key in keys:
                rows[variant][key].append(got[key])
    out: dict[str, dict] = {}
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
    if "localiser" in rows:
        found = np.concatenate(rows["localiser"]["poses"])
        for variant in (v for v in variants if v != "localiser"):
            given = np.concatenate(rows[variant]["poses"])
            both = np.isfinite(found[:, 0, 0]) & np.isfinite(given[:, 0, 0])
            out["localiser"][f"gap_to_{variant}_mm"] = float(np.median(anchors.ed(found[both], given[both]))) \
                if both.any() else None
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=2_000_000)
    ap.add_argument("--localiser", default=str(DEFAULT_LOCALISERS_DIR / "default" / "model.onnx"))
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--stacks", type=int, default=1, help="stacks of one head sent together in each request")
    ap.add_argument("--motion", default=None, help="the head's motion: a pose benchmark's level (default: the "
                                                   "generator's own drift)")
    ap.add_argument("--planning", default="independent", choices=PLANNINGS,
                    help="the stacks' orientations about the head: each its own, or orthogonal as a scan is planned")
    args = ap.parse_args()
    result = pose_accuracy(validation_cases(args.scenes, args.seed, args.stacks, motion=args.motion,
                                            planning=args.planning),
                           pose_estimator(), Localiser.load(args.localiser), tuple(args.variants.split(",")))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
