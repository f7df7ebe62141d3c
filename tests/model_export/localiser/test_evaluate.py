"""The localiser's figures: Dice, and the E.D. between two answers' slice poses computed in the
slice frame (the voxel -> slice map undone), against poses simulated with a known offset."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from model_export.localiser.evaluate import median_ed, dice
from service.geometry.pose import make_pose
from service.io.volume import Volume
from service.preprocess.stack import split_stack


def test_dice_counts_overlap_and_two_empty_masks_agree() -> None:
    a = np.zeros((4, 4, 4), bool)
    assert dice(a, a) == 1.0
    b = a.copy()
    b[0] = True
    assert dice(a, b) == 0.0 and dice(b, b) == 1.0


def test_the_ed_between_answers_is_the_offset_of_their_slice_poses() -> None:
    vol = Volume(np.zeros((20, 16, 5), np.float32), np.diag([1.5, 1.5, 3.0, 1.0]))
    slices = split_stack(vol, np.ones(vol.array.shape, bool))
    rotations = Rotation.random(5, random_state=0).as_matrix()
    poses = [make_pose(r, t) for r, t in zip(rotations, np.random.default_rng(0).normal(size=(5, 3)) * 20)]
    shift = make_pose(np.eye(3), np.array([3.0, 4.0, 0.0]))                       # 5 mm, in atlas space
    def answer(ps: list[np.ndarray], empty: int = -1) -> dict:
        return {"slices": [{"reason": "empty" if k == empty else None,
                            "atlas_from_voxel": (p @ slices.slice_from_voxel[k]).tolist()} for k, p in enumerate(ps)]}
    prepared = [SimpleNamespace(slices=slices)]
    same, n = median_ed([answer(poses)], [answer(poses)], prepared)
    assert n == 5 and same < 1e-9
    moved, n = median_ed([answer(poses)], [answer([shift @ p for p in poses], empty=2)], prepared)
    assert n == 4 and abs(moved - 5.0) < 1e-9


def test_a_scan_folder_pairs_each_stack_with_its_manual_mask(tmp_path) -> None:  # noqa: ANN001
    from model_export.localiser.evaluate import masked_files

    for name in ("b.nii.gz", "b_brain_mask.nii.gz", "a.nii.gz", "a_brain_mask.nii.gz", "c.nii.gz"):
        (tmp_path / name).write_bytes(b"")
    assert masked_files(tmp_path) == [("a", tmp_path / "a.nii.gz", tmp_path / "a_brain_mask.nii.gz"),
                                      ("b", tmp_path / "b.nii.gz", tmp_path / "b_brain_mask.nii.gz")]   # c has no mask
    assert masked_files(tmp_path / "absent") == []
