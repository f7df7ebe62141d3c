"""End to end through the app: every slice's atlas_from_voxel against simulated ground truth.

Stacks are acquired from a phantom brain in atlas space with known per-slice motion; the estimator
is swapped for an oracle that returns the true atlas pose of each PREPROCESSED slice, computed here
independently of the service (plane axes from the stack's voxel axes, origin at the world centroid
of the slice's mask). The service must then compose crop/centre/resampling and the pose into
``atlas_from_voxel`` equal to the truth ``motion[s] @ affine`` to well under 1 mm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import SimpleITK as sitk

from client.slice_transforms import transform_files
from service.geometry import se3, sampling
from service.geometry.anchors import ed
from service.geometry.pose import apply, index_reversal, make_pose, translate
from service.io.volume import Volume, read_volume, write_volume
from service.preprocess.intensity import rescale_0_255
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

nib = pytest.importorskip("nibabel", reason="nibabel (dev extra) writes the nibabel case")

BRAIN = phantom_brain(0)
OBLIQUE = se3.so3_exp(np.array([0.35, -0.25, 0.6]))
LEFT_HANDED = np.diag([-1.0, 1.0, 1.0])
LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def motion(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centre = np.array([0.0, 3.0, 8.0])
    g = se3.exp(np.concatenate([rng.normal(scale=0.08, size=(n, 3)), rng.normal(scale=2.0, size=(n, 3))], 1))
    to_c = make_pose(np.eye(3), centre)
    return to_c @ g @ se3.inverse(to_c)


def write(path: Path, array: np.ndarray, affine: np.ndarray, writer: str) -> None:
    if writer == "simpleitk":
        write_volume(Volume(array, affine), path)
    else:
        nib.save(nib.Nifti1Image(array, affine), str(path))


def true_network_poses(affine: np.ndarray, mask: np.ndarray, axis: int, g: np.ndarray) -> np.ndarray:
    """Atlas pose of each centred slice plane: x along voxel axis p, y along q, origin at the mask centroid."""
    p, q = [a for a in range(3) if a != axis]
    cols = affine[:3, :3] / np.linalg.norm(affine[:3, :3], axis=0)
    rot = np.stack([cols[:, p], cols[:, q], np.cross(cols[:, p], cols[:, q])], axis=1)
    out = []
    for s in range(mask.shape[axis]):
        idx = np.argwhere(np.take(mask, s, axis=axis))
        if len(idx):
            inplane = idx.mean(0)
        else:
            inplane = (np.delete(np.array(mask.shape), axis) - 1) / 2.0
        voxel = np.insert(inplane, axis, s)
        out.append(g[s] @ make_pose(rot, apply(affine, voxel)))
    return np.array(out)


CASES = [
    ("simpleitk", 2, np.eye(3)), ("simpleitk", 0, np.eye(3)), ("simpleitk", 1, OBLIQUE),
    ("nibabel", 1, np.eye(3)), ("nibabel", 2, OBLIQUE), ("nibabel", 0, LEFT_HANDED),
]


def two_still_stacks(tmp_path: Path) -> tuple[list[tuple], list[np.ndarray]]:
    """An axial and an oblique coronal stack of the same, still fetus: the upload's form files and
    each stack's true network-frame poses."""
    files, truths = [], []
    for i, (axis, rotation) in enumerate([(2, np.eye(3)), (1, OBLIQUE)]):
        shape = [44, 44, 44]
        shape[axis] = 18
        aff = stack_affine(axis, rotation, 1.5, 3.5, tuple(shape))
        g = np.repeat(np.eye(4)[None], shape[axis], axis=0)          # the fetus still
        img, msk = acquire_stack(*BRAIN, aff, tuple(shape), axis, g)
        write(tmp_path / f"s{i}.nii.gz", img, aff, "simpleitk")
        write(tmp_path / f"m{i}.nii.gz", msk.astype(np.uint8), aff, "simpleitk")
        truths.append(true_network_poses(aff, msk, axis, g))
        files += [("stacks", (f"s{i}.nii.gz", (tmp_path / f"s{i}.nii.gz").read_bytes())),
                  ("masks", (f"m{i}.nii.gz", (tmp_path / f"m{i}.nii.gz").read_bytes()))]
    return files, truths


def stacks_apart(truths: list[np.ndarray], rng: np.random.Generator, shift_z_mm: float, noise: float) -> np.ndarray:
    """What an oracle network answers for :func:`two_still_stacks`: the second stack moved about the
    brain's centre by (2, -2.5, 2) deg and (2.5, -2, ``shift_z_mm``) mm, every slice a further
    ``noise`` deg and mm off on its own (normal)."""
    centre = make_pose(np.eye(3), [0.0, 3.0, 8.0])
    offset = centre @ se3.exp(np.array([*np.radians([2.0, -2.5, 2.0]), 2.5, -2.0, shift_z_mm])) @ se3.inverse(centre)
    given = np.concatenate([truths[0], offset @ truths[1]])
    return given @ se3.exp(np.concatenate([rng.normal(0, np.radians(noise), (len(given), 3)),
                                           rng.normal(0, noise, (len(given), 3))], 1))


@pytest.mark.parametrize(("writer", "axis", "rotation"), CASES, ids=[f"{w}-axis{a}-{i}" for i, (w, a, _) in enumerate(CASES)])
def test_atlas_from_voxel_matches_truth(oracle, oracle_client, tmp_path: Path, writer: str, axis: int,
                                        rotation: np.ndarray) -> None:
    shape = [44, 44, 44]
    shape[axis] = 18
    shape = tuple(shape)
    aff = stack_affine(axis, rotation, 1.5, 3.5, shape)
    g = motion(shape[axis], seed=axis)
    img, msk = acquire_stack(*BRAIN, aff, shape, axis, g)
    write(tmp_path / "stack.nii.gz", img, aff, writer)
    write(tmp_path / "mask.nii.gz", msk.astype(np.uint8), aff, writer)
    oracle.truth = true_network_poses(aff, msk, axis, g)
    with open(tmp_path / "stack.nii.gz", "rb") as s, open(tmp_path / "mask.nii.gz", "rb") as m:
        r = oracle_client.post("/v1/predict", files=[("stacks", ("stack.nii.gz", s)), ("masks", ("mask.nii.gz", m))],
                               data={"bias_correction": "false", "mc_samples": "5"})
    assert r.status_code == 200, r.text
    body = r.json()
    stack = body["stacks"][0]
    assert stack["slice_axis"] == axis and stack["shape"] == list(shape)
    assert [s["index"] for s in stack["slices"]] == list(range(shape[axis]))
    np.testing.assert_allclose(stack["scanner_from_voxel"], aff, atol=1e-4)          # the file's own voxel -> RAS
    assert 0.0 <= stack["noise"]["input_noise"] < 0.06 and stack["noise"]["beyond_calibration"] is False  # noise-free
    assert stack["noise"]["expected_error_added_mm"] == 0.0
    assert set(stack["frame"]) == {"request_network_error_mm", "expected_error_added_mm"}   # the oracle's model: none
    assert stack["frame"]["expected_error_added_mm"] == 0.0
    # Each slice's ITK transform (client side, from the answer alone) takes the atlas point a voxel
    # shows to where the file puts that voxel, both in ITK's LPS.
    for name, text in transform_files(body).items():
        if name.endswith(".tfm"):
            k = int(name[-7:-4])
            (tmp_path / "t.tfm").write_text(text)
            itk = sitk.ReadTransform(str(tmp_path / "t.tfm"))
            voxel = np.insert(np.array([[3.0, 40.0], [17.0, 5.0]]), axis, k, axis=1)
            atlas_lps = apply(LPS @ np.array(stack["slices"][k]["atlas_from_voxel"]), voxel)
            moved = np.array([itk.TransformPoint(tuple(p)) for p in atlas_lps])
            np.testing.assert_allclose(moved, apply(LPS @ aff, voxel), atol=1e-3)
    worst = {"network_atlas_from_voxel": 0.0, "atlas_from_voxel": 0.0}
    for s in stack["slices"]:
        corners = np.array([[0, 0, 0], [shape[0] - 1, shape[1] - 1, shape[2] - 1], [shape[0] - 1, 0, 0]], float)
        corners[:, axis] = s["index"]
        want = apply(g[s["index"]] @ aff, corners)
        for key in worst:
            if key == "atlas_from_voxel" and s["reason"] == "empty":
                continue                       # an empty slice takes the stack model's pose
            worst[key] = max(worst[key], float(np.abs(apply(np.array(s[key]), corners) - want).max()))
    # The network's own pose composes exactly; stack consistency (on by default) fuses it with the
    # stack model by inverse variance: an exact oracle (no MC spread) keeps its pose.
    assert worst["network_atlas_from_voxel"] < 0.01, worst
    assert worst["atlas_from_voxel"] < 0.05, worst
    assert stack["consistency"]["decidable"] and stack["consistency"]["twinned_slices"] == 0
    # an exact oracle's poses are expected to be exact; an empty slice's (the stack model's) less so
    expected = [s["expected_error_mm"] for s in stack["slices"] if s["reason"] != "empty"]
    assert None not in expected and max(expected) < 0.5, expected
    s0 = stack["slices"][shape[axis] // 2]
    np.testing.assert_allclose(s0["translation_mm"], oracle.truth[shape[axis] // 2][:3, 3], atol=0.05)

    # Content: each network input is the phantom seen at its true centred pose (crop/centre consistent).
    truth = oracle.truth
    rendered = sampling.sample_slices(BRAIN[0], BRAIN[2], truth, 64, 2.0)
    rmask = sampling.sample_slices(BRAIN[1], BRAIN[2], truth, 64, 2.0) > 0.5
    expected = rescale_0_255(rendered, rmask)
    seen = oracle.seen
    for k in range(len(truth)):
        if rmask[k].mean() > 0.1:
            cc = np.corrcoef(seen[k].ravel(), expected[k].ravel())[0, 1]
            assert cc > 0.85, (k, cc)


def test_two_stacks_of_one_position_are_pooled_and_stay_exact(oracle, oracle_client, tmp_path: Path) -> None:
    """Two stacks (axial, oblique coronal) of the same, still fetus, an exact oracle: the response
    says both were pooled with no spread between them, each stack's pooled position is the same
    ``atlas_from_scanner``, and the poses stay exact (pooling moves nothing that agrees)."""
    files, truths = two_still_stacks(tmp_path)
    oracle.truth = np.concatenate(truths)
    r = oracle_client.post("/v1/predict", files=files, data={"bias_correction": "false", "mc_samples": "5",
                                                             "image_consistency": "false"})
    assert r.status_code == 200, r.text
    reports = [s["consistency"] for s in r.json()["stacks"]]
    assert all(c["image_consistency"] is None for c in reports)
    assert [c["stacks_pooled"] for c in reports] == [2, 2]
    assert all(c["between_stacks_sd_mm"] < 0.1 for c in reports)
    pooled = np.array([c["pooled_atlas_from_scanner"] for c in reports])
    np.testing.assert_allclose(pooled[0], pooled[1], atol=0.05)
    np.testing.assert_allclose(pooled[0], reports[0]["atlas_from_scanner"], atol=0.05)
    for stack in r.json()["stacks"]:
        for s in stack["slices"]:
            if s["reason"] != "empty":
                np.testing.assert_allclose(np.array(s["atlas_from_voxel"]), np.array(s["network_atlas_from_voxel"]),
                                           atol=0.05)


def test_two_stacks_are_refined_where_their_slices_cross(oracle, oracle_client, tmp_path: Path) -> None:
    """Two stacks of a still fetus; the network puts the second 4 deg / 4 mm off the first as a whole
    (each slice a further 0.5 deg / 0.5 mm off on its own; the MC spread says 4 mm). Each stack is
    consistent on its own, so only the images can tell: where the slices cross they pull the stacks
    together. What images can correct (the poses relative to each other: the E.D. once the one rigid
    map that best takes all poses to the truth is applied) drops with ``image_consistency`` to under
    0.6 of what it is without (measured: 1.82 -> 0.81 mm); the report says what it did."""
    files, truths = two_still_stacks(tmp_path)
    truth = np.concatenate(truths)
    oracle.truth = stacks_apart(truths, np.random.default_rng(5), 2.5, 0.5)
    oracle.spread_mm = 4.0
    relative = {}
    for on in ("true", "false"):
        r = oracle_client.post("/v1/predict", files=files, data={"bias_correction": "false", "mc_samples": "5",
                                                                 "image_consistency": on})
        assert r.status_code == 200, r.text
        out = [s for st in r.json()["stacks"] for s in st["slices"]]
        keep = np.array([s["reason"] is None for s in out])
        network = np.array([s["network_atlas_from_voxel"] for s in out])
        returned = (np.array([s["atlas_from_voxel"] for s in out]) @ np.linalg.inv(network) @ oracle.truth)[keep]
        frame = se3.frechet_mean(truth[keep] @ se3.inverse(returned), np.ones(int(keep.sum())))
        relative[on] = ed(frame @ returned, truth[keep]).mean()
        reports = [st["consistency"]["image_consistency"] for st in r.json()["stacks"]]
        if on == "true":
            assert all(c["stacks"] == 2 and c["pairs"] > 50 and c["slices_refined"] > 5 for c in reports), reports
            assert all(c["mismatch_after"] < c["mismatch_before"] for c in reports), reports
        else:
            assert reports == [None, None]
    assert relative["true"] < 0.6 * relative["false"], relative


def test_a_stack_acquired_again_in_its_orientation_loses_nothing_to_the_image_stage(oracle, oracle_client,
                                                                                  tmp_path: Path) -> None:
    """An axial stack and its repeat (the same planning, half a slice along: the usual remedy for a
    corrupted stack): no slice of one crosses the other's, so the images check nothing, and the
    answer is the one without the image stage (its expected errors were multiplied as for slices
    on no line, and most slices lost their accept flag)."""
    files, truths = [], []
    for i, shift in enumerate((0.0, 1.75)):
        shape = (44, 44, 18)
        aff = stack_affine(2, np.eye(3), 1.5, 3.5, shape)
        aff[:3, 3] += aff[:3, 2] / 3.5 * shift
        g = np.repeat(np.eye(4)[None], 18, axis=0)
        img, msk = acquire_stack(*BRAIN, aff, shape, 2, g)
        write(tmp_path / f"s{i}.nii.gz", img, aff, "simpleitk")
        write(tmp_path / f"m{i}.nii.gz", msk.astype(np.uint8), aff, "simpleitk")
        truths.append(true_network_poses(aff, msk, 2, g))
        files += [("stacks", (f"s{i}.nii.gz", (tmp_path / f"s{i}.nii.gz").read_bytes())),
                  ("masks", (f"m{i}.nii.gz", (tmp_path / f"m{i}.nii.gz").read_bytes()))]
    oracle.truth = stacks_apart(truths, np.random.default_rng(6), 1.0, 0.5)
    oracle.spread_mm = 2.0
    on = answered(oracle_client, [files], bias_correction="false", mc_samples="5")[0]
    off = answered(oracle_client, [files], bias_correction="false", mc_samples="5", image_consistency="false")[0]
    assert [st["consistency"]["image_consistency"] for st in on] == [None, None]
    for a, b in zip(on, off):
        assert [s["expected_error_mm"] for s in a["slices"]] == [s["expected_error_mm"] for s in b["slices"]]
        assert [s["accepted"] for s in a["slices"]] == [s["accepted"] for s in b["slices"]]


def rewritten(files: list[tuple], tmp_path: Path, field: str, change) -> list[tuple]:  # noqa: ANN001
    """The upload ``files`` with each file of ``field`` (``stacks`` or ``masks``) read, changed by
    ``change`` (a :class:`Volume` -> :class:`Volume`) and written again under its own name."""
    out = []
    for f, (name, data) in files:
        if f == field:
            (tmp_path / name).write_bytes(data)
            write_volume(change(read_volume(tmp_path / name)), tmp_path / f"rewritten-{name}")
            data = (tmp_path / f"rewritten-{name}").read_bytes()
        out.append((f, (name, data)))
    return out


def answered(client, uploads: list[list[tuple]], **form: str) -> list[list[dict]]:  # noqa: ANN001
    """Each upload's ``/v1/predict`` stacks (200 asserted), the form fields ``form``."""
    answers = []
    for upload in uploads:
        r = client.post("/v1/predict", files=upload, data=form)
        assert r.status_code == 200, r.text
        answers.append(r.json()["stacks"])
    return answers


def test_where_the_files_put_the_scanners_origin_changes_no_pose(oracle, oracle_client, tmp_path: Path) -> None:
    """The scanner's origin (its table position) is the files' choice, not the fetus's. Two stacks of
    a still fetus, the network 2-4 deg / mm off per stack and 1 deg / 1 mm per slice, every stage on;
    the same files with every affine moved by 300 mm give the same ``atlas_from_voxel``, and the
    stage's placements move with the scanner frame."""
    files, truths = two_still_stacks(tmp_path)
    oracle.truth = stacks_apart(truths, np.random.default_rng(8), 4.0, 1.0)
    oracle.spread_mm = 3.0
    shift = np.array([200.0, 150.0, -100.0])
    moved = lambda vol: Volume(vol.array, translate(shift) @ vol.affine)  # noqa: E731
    moved_files = rewritten(rewritten(files, tmp_path, "stacks", moved), tmp_path, "masks", moved)
    for here, there in zip(*answered(oracle_client, [files, moved_files], bias_correction="false", mc_samples="5")):
        assert here["consistency"]["decidable"] and here["consistency"]["image_consistency"] is not None
        a = np.array([s["atlas_from_voxel"] for s in here["slices"]])
        b = np.array([s["atlas_from_voxel"] for s in there["slices"]])
        assert np.abs(a[:, :3, 3] - b[:, :3, 3]).max() < 1e-3 and np.abs(a[:, :3, :3] - b[:, :3, :3]).max() < 1e-5
        for key in ("atlas_from_scanner", "pooled_atlas_from_scanner"):
            np.testing.assert_allclose(np.array(there["consistency"][key]),
                                       np.array(here["consistency"][key]) @ translate(-shift), atol=1e-3)


def test_stacks_stored_with_an_offset_or_as_z_scores_get_what_their_magnitudes_get(oracle, oracle_client,
                                                                                     tmp_path: Path) -> None:
    """A magnitude image stored with values below zero (a signed export's offset, a z-score) or with its
    air lifted above zero (a scale and an intercept) is the same image: with N4 and every stage on, the network sees the same inputs and the answer is the same
    (before, N4 clipped the dark half of a z-scored brain to 0 and the localiser's scaling took the
    offset for the image)."""
    files, truths = two_still_stacks(tmp_path)
    oracle.truth = stacks_apart(truths, np.random.default_rng(9), 3.0, 1.0)
    oracle.spread_mm = 3.0
    stored = {"offset": lambda a: a - 1000.0, "z-score": lambda a: (a - a.mean()) / a.std(),
              "air lifted": lambda a: a * 0.5 + 1000.0}
    answers, inputs = {}, {}
    for how in ("as acquired", *stored):
        upload = files if how == "as acquired" else rewritten(
            files, tmp_path, "stacks", lambda vol: Volume(stored[how](vol.array.astype(np.float32)), vol.affine))
        [stacks] = answered(oracle_client, [upload], bias_correction="true", mc_samples="5")
        answers[how] = np.array([s["atlas_from_voxel"] for st in stacks for s in st["slices"]])
        inputs[how] = oracle.seen.copy()
    for how in stored:
        np.testing.assert_allclose(inputs[how], inputs["as acquired"], atol=0.05)
        np.testing.assert_allclose(answers[how], answers["as acquired"], atol=1e-3)


def test_a_mask_file_that_stores_the_stacks_voxels_in_another_order_gives_the_same_answer(oracle, oracle_client,
                                                                                            tmp_path: Path) -> None:
    """Each mask written as a tool that reorients its files writes it (its first axis reversed and its
    first two axes swapped, the header saying so: the same voxels in the world) gives the answer
    the stack's own grid gives (it was a 422 for a grid "not the stack's")."""
    files, truths = two_still_stacks(tmp_path)
    oracle.truth = stacks_apart(truths, np.random.default_rng(10), 3.0, 1.0)
    oracle.spread_mm = 3.0
    def turned(vol: Volume) -> Volume:                    # its first axis reversed, then its first two swapped
        affine = vol.affine @ index_reversal(0, vol.array.shape[0]) @ np.eye(4)[:, [1, 0, 2, 3]]
        return Volume(np.ascontiguousarray(np.asarray(vol.array)[::-1].transpose(1, 0, 2)), affine)

    reoriented = rewritten(files, tmp_path, "masks", turned)
    for here, there in zip(*answered(oracle_client, [files, reoriented], bias_correction="true", mc_samples="5")):
        assert here["localisation"] == there["localisation"]
        np.testing.assert_allclose([s["atlas_from_voxel"] for s in there["slices"]],
                                   [s["atlas_from_voxel"] for s in here["slices"]], atol=1e-6)


def test_the_same_stacks_in_another_order_get_the_same_poses(oracle, oracle_client, tmp_path: Path) -> None:
    """Two stacks of a still fetus, the network off per stack and per slice, every stage on: sent the
    other way round (stacks and masks), each stack's slices get the same ``atlas_from_voxel`` and
    expected errors to the bit (the stages run over the stacks in one order whatever the request's)."""
    files, truths = two_still_stacks(tmp_path)
    rng = np.random.default_rng(9)
    centre = make_pose(np.eye(3), [0.0, 3.0, 8.0])
    offset = centre @ se3.exp(np.array([*np.radians([2.0, -2.5, 2.0]), 2.5, -2.0, 4.0])) @ se3.inverse(centre)
    noise = [se3.exp(np.concatenate([rng.normal(0, np.radians(1.0), (len(t), 3)), rng.normal(0, 1.0, (len(t), 3))], 1))
             for t in truths]
    given = [truths[0] @ noise[0], offset @ truths[1] @ noise[1]]
    oracle.spread_mm = 3.0
    answers = []
    for order in ([0, 1], [1, 0]):
        oracle.truth = np.concatenate([given[i] for i in order])
        upload = [files[2 * i] for i in order] + [files[2 * i + 1] for i in order]
        r = oracle_client.post("/v1/predict", files=upload, data={"bias_correction": "false", "mc_samples": "5"})
        assert r.status_code == 200, r.text
        stacks = r.json()["stacks"]
        answers.append([[(s["atlas_from_voxel"], s["expected_error_mm"]) for s in stacks[order.index(i)]["slices"]]
                        for i in (0, 1)])
        assert all(st["consistency"]["image_consistency"] is not None for st in stacks)
    assert answers[0] == answers[1]                              # JSON floats: equal to the bit


def test_a_stack_whose_file_stores_its_slices_last_to_first_gets_the_same_poses(oracle, oracle_client,
                                                                                tmp_path: Path) -> None:
    """Two stacks of a still fetus, the network off per stack and per slice, every stage and N4 on:
    the second stack's file written again with its slices last to first (its affine so, each slice
    where it was) gives each slice the same place in the atlas (before: N4 shrank the stack from its
    first voxel, and the image stage named slices by their index)."""
    files, truths = two_still_stacks(tmp_path)
    rng = np.random.default_rng(4)
    noise = [se3.exp(np.concatenate([rng.normal(0, np.radians(1.0), (len(t), 3)), rng.normal(0, 1.0, (len(t), 3))], 1))
             for t in truths]
    given = [truths[0] @ noise[0], truths[1] @ noise[1]]
    oracle.spread_mm = 3.0
    axis = 1                                                        # the second stack's slice axis
    n = len(truths[1])
    flip = index_reversal(axis, n)                                  # new voxel index -> old
    for name in ("s1", "m1"):
        vol = read_volume(tmp_path / f"{name}.nii.gz")
        write(tmp_path / f"{name}r.nii.gz", np.flip(vol.array, axis).copy(), vol.affine @ flip, "simpleitk")
    stored = files[:2] + [("stacks", ("s1.nii.gz", (tmp_path / "s1r.nii.gz").read_bytes())),
                          ("masks", ("m1.nii.gz", (tmp_path / "m1r.nii.gz").read_bytes()))]
    answers = []
    for upload, second in ((files, given[1]), (stored, given[1][::-1])):
        oracle.truth = np.concatenate([given[0], second])
        r = oracle_client.post("/v1/predict", files=upload, data={"mc_samples": "5"})
        assert r.status_code == 200, r.text
        stacks = r.json()["stacks"]
        assert all(st["consistency"]["image_consistency"] is not None for st in stacks)
        answers.append([np.array([s["atlas_from_voxel"] for s in st["slices"]]) for st in stacks])
    (first, second), (first_r, second_r) = answers
    np.testing.assert_allclose(first_r, first, atol=1e-4)
    np.testing.assert_allclose(second_r[::-1] @ np.linalg.inv(flip), second, atol=1e-4)


def test_a_stack_that_does_not_decide_its_branch_takes_the_other_stacks(oracle, oracle_client, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Two stacks of the same still fetus; the second comes from the network wholly on its twin and
    1 mm / 1 deg off per slice. With the margin a stack needs to decide its own branch set between
    the two stacks' margins (exact: ~1e15; noisy: ~3e2), only the first decides; the second takes
    the branch nearer to the first's placement: every slice back from the twin, its placement that
    of the first stack, and the response says whose word it took."""
    import service.consistency.stack_fit as stack_fit_module
    from service.geometry import twin

    monkeypatch.setattr(stack_fit_module, "MIN_STACK_BRANCH_MARGIN", 1e5)
    rng = np.random.default_rng(12)
    files, (first_truth, second_truth) = two_still_stacks(tmp_path)
    noise = np.concatenate([rng.normal(0, np.radians(1.0), (len(second_truth), 3)),
                            rng.normal(0, 1.0, (len(second_truth), 3))], 1)
    oracle.truth = np.concatenate([first_truth, twin.twin(second_truth @ se3.exp(noise))])
    r = oracle_client.post("/v1/predict", files=files, data={"bias_correction": "false", "mc_samples": "5"})
    assert r.status_code == 200, r.text
    first, second = (s["consistency"] for s in r.json()["stacks"])
    assert first["branch_decided"] and not first["branch_from_request"]
    assert second["decidable"] and not second["branch_decided"] and second["branch_from_request"]
    used = [s for s in r.json()["stacks"][1]["slices"] if s["reason"] != "empty"]
    assert used and all(s["branch"] == "twin" for s in used)
    a, b = np.array(first["atlas_from_scanner"]), np.array(second["atlas_from_scanner"])
    assert np.linalg.norm(a[:3, 3] - b[:3, 3]) < 3.0
    assert np.degrees(np.linalg.norm(se3.so3_log(a[:3, :3].T @ b[:3, :3]))) < 2.0


def test_a_given_acquisition_order_is_used_and_keeps_the_poses_exact(oracle, oracle_client, tmp_path: Path) -> None:
    """``slice_order``: the stage fits its motion over the order the request gives (the report says
    ``given``), a named family restricts its choice, and the poses it keeps stay exact with an exact oracle."""
    shape, axis = (44, 44, 18), 2
    aff = stack_affine(axis, OBLIQUE, 1.5, 3.5, shape)
    g = motion(shape[axis], seed=4)
    img, msk = acquire_stack(*BRAIN, aff, shape, axis, g)
    write(tmp_path / "stack.nii.gz", img, aff, "simpleitk")
    write(tmp_path / "mask.nii.gz", msk.astype(np.uint8), aff, "simpleitk")
    oracle.truth = true_network_poses(aff, msk, axis, g)
    files = [("stacks", ("stack.nii.gz", (tmp_path / "stack.nii.gz").read_bytes())),
             ("masks", ("mask.nii.gz", (tmp_path / "mask.nii.gz").read_bytes()))]
    given = ",".join(str(k) for k in [*range(0, 18, 2), *range(1, 18, 2)])
    for order, said in ((given, {"given"}), ("interleaved", {"interleaved-even-first", "interleaved-odd-first"}),
                        ("sequential", {"sequential"})):
        r = oracle_client.post("/v1/predict", files=files,
                               data={"bias_correction": "false", "mc_samples": "5", "slice_order": order})
        assert r.status_code == 200, r.text
        stack = r.json()["stacks"][0]
        assert stack["consistency"]["acquisition_order"] in said, (order, stack["consistency"])
        kept = [s for s in stack["slices"] if s["reason"] not in ("empty", "inconsistent_with_stack")]
        assert len(kept) >= 15                 # i.i.d. jitter: an end slice the others cannot predict is flagged
        for s in kept:
            np.testing.assert_allclose(s["atlas_from_voxel"], s["network_atlas_from_voxel"], atol=0.05)


def test_a_dicom_series_acquisition_times_order_its_stack(oracle, oracle_client, tmp_path: Path) -> None:
    """A zipped DICOM series whose slices carry interleaved acquisition times: the stage fits over
    that order (``acquisition-times``) unless the request says otherwise; the poses it keeps stay exact."""
    import zipfile

    from tests.io.test_readers import _write_series

    shape, axis = (44, 44, 18), 2
    aff = stack_affine(axis, OBLIQUE, 1.5, 3.5, shape)
    g = motion(shape[axis], seed=6)
    img, msk = acquire_stack(*BRAIN, aff, shape, axis, g)
    rank = np.argsort([*range(0, 18, 2), *range(1, 18, 2)])            # slice k acquired rank[k]-th
    times = [f"1015{rank[k] // 10:02d}.{rank[k] % 10}" for k in range(18)]
    files = _write_series(tmp_path, Volume(np.round(img * 1000 / img.max()), aff), "1.2.3.555", times)
    with zipfile.ZipFile(tmp_path / "series.zip", "w") as z:
        for p in files:
            z.write(p, p.name)
    write(tmp_path / "mask.nii.gz", msk.astype(np.uint8), aff, "simpleitk")
    oracle.truth = true_network_poses(aff, msk, axis, g)
    upload = [("stacks", ("series.zip", (tmp_path / "series.zip").read_bytes())),
              ("masks", ("mask.nii.gz", (tmp_path / "mask.nii.gz").read_bytes()))]
    for extra, said in (({}, "acquisition-times"), ({"slice_order": "sequential"}, "sequential")):
        r = oracle_client.post("/v1/predict", files=upload, data={"bias_correction": "false", "mc_samples": "5", **extra})
        assert r.status_code == 200, r.text
        stack = r.json()["stacks"][0]
        assert stack["consistency"]["acquisition_order"] == said
        np.testing.assert_allclose(stack["scanner_from_voxel"], aff, atol=1e-3)    # the series' own geometry
        kept = [s for s in stack["slices"] if s["reason"] not in ("empty", "inconsistent_with_stack")]
        assert len(kept) >= 15                 # i.i.d. jitter: an end slice the others cannot predict is flagged
        for s in kept:
            np.testing.assert_allclose(s["atlas_from_voxel"], s["network_atlas_from_voxel"], atol=0.05)


def test_a_stack_stored_with_its_in_plane_axes_swapped_and_rows_reversed_gets_the_same_poses(real_client,
                                                                                            tmp_path: Path) -> None:  # noqa: ANN001
    """A real (tiny, random) network with its MC dropout and test-time views, every stage and N4 on:
    the oblique coronal stack's file written again with its in-plane axes swapped and its rows
    reversed (its mask alike, the header saying so) gives each slice the same place in the atlas.
    The slices are laid out by the scanner's axes, so the network sees the same pictures through the
    same views with the same draws (before: another view per picture, other draws, other poses)."""
    files, _ = two_still_stacks(tmp_path)
    vol, msk = read_volume(tmp_path / "s1.nii.gz"), read_volume(tmp_path / "m1.nii.gz")
    n = vol.array.shape[2]                                          # its slices lie along voxel axis 1
    old_from_new = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, n - 1.0], [0.0, 0.0, 0.0, 1.0]])
    for name, v in (("s1t", vol), ("m1t", msk)):
        write(tmp_path / f"{name}.nii.gz", np.ascontiguousarray(np.flip(np.swapaxes(v.array, 0, 2), 0)),
              v.affine @ old_from_new, "simpleitk")
    stored = [("stacks", ("s1.nii.gz", (tmp_path / "s1t.nii.gz").read_bytes())),
              ("masks", ("m1.nii.gz", (tmp_path / "m1t.nii.gz").read_bytes()))]
    answers = []
    for upload in (files[2:], stored):
        r = real_client.post("/v1/predict", files=upload, data={"mc_samples": "10"})
        assert r.status_code == 200, r.text
        answers.append(np.array([s["atlas_from_voxel"] for s in r.json()["stacks"][0]["slices"]]))
    as_stored, turned = answers
    np.testing.assert_allclose(turned, as_stored @ old_from_new, atol=1e-4)
