"""Per-stack rigid transform from slice poses: the twin in voxel indices, robustness to outliers and twins."""

from __future__ import annotations

import numpy as np

from service.geometry import se3, twin
from service.io.volume import Volume
from service.preprocess.stack import split_stack
from service.reconstruction.stack_rigid import fit_stack_rigid, twin_atlas_from_voxel
from tests.reconstruction.helpers import perturb


def test_twin_in_voxel_indices_is_the_twin_of_the_slice_pose():
    rng = np.random.default_rng(0)
    for flip in (1.0, -1.0):                                # right- and left-handed voxel axes
        affine = np.diag([0.9, flip * 1.1, 3.5, 1.0])
        affine[:3, 3] = [-20.0, 10.0, 4.0]
        vol = Volume(np.ones((6, 7, 5), np.float32), affine)
        s = split_stack(vol, np.ones((6, 7, 5), bool))
        pose = se3.exp(rng.normal(size=(5, 6)) * [0.5, 0.5, 0.5, 10, 10, 10])
        a = pose @ s.slice_from_voxel
        got = twin_atlas_from_voxel(a, np.full(5, s.slice_axis), np.arange(5), 1.3)
        assert np.allclose(got, twin.twin(pose, 1.3) @ s.slice_from_voxel)
        assert np.allclose(twin_atlas_from_voxel(got, np.full(5, 2), np.arange(5), 1.3), a)


def test_fit_recovers_the_stacks_despite_noise_gross_errors_and_twins(acquisition):
    """Slices at their stack's transform, each moved by N(0, 3 mm) / N(0, 3 deg) per axis; 10 % moved
    by 40 mm more, 15 % replaced by their twin (plane x = 0). With about 17 slices per stack the
    mean of the noise alone is expected at ~1.3 mm / 1.3 deg (measured up to 1.6 mm and 0.9 deg);
    thresholds 2.5 mm / 2.5 deg. The gross errors are flagged, the twins put on the stack's branch."""
    ss = acquisition.slice_set()
    truth = fit_stack_rigid(ss).atlas_from_scanner          # the stacks' transforms of the phantom
    exact = truth[ss.stack_index] @ ss.stack_affine
    rng = np.random.default_rng(3)
    poses = perturb(exact, rng, 3.0, 3.0, ss.centres(exact))
    inc = np.flatnonzero(ss.include)
    gross = rng.choice(inc, len(inc) // 10, replace=False)
    poses[gross, :3, 3] += rng.choice([-40.0, 40.0], size=(len(gross), 3))
    rest = np.setdiff1d(inc, gross)
    twins = rng.choice(rest, int(0.15 * len(inc)), replace=False)
    poses[twins] = twin_atlas_from_voxel(poses[twins], ss.slice_axis[twins], ss.slice_index[twins], 0.0)
    fit = fit_stack_rigid(ss, poses, plane_x_mm=0.0)
    for s in range(3):
        err = se3.inverse(truth[s]) @ fit.atlas_from_scanner[s]
        centre = ss.centres(ss.stack_affine)[ss.stack_index == s].mean(0)
        assert np.linalg.norm(err[:3, :3] @ centre + err[:3, 3] - centre) < 2.5
        assert np.degrees(np.linalg.norm(se3.so3_log(err[:3, :3]))) < 2.5
    assert not fit.inlier[gross].any()
    assert fit.inlier[rest].mean() > 0.9
    branch = fit.branch_poses(ss, poses, 0.0)
    d = np.linalg.norm(ss.positions(branch) - ss.positions(exact), axis=1)
    per_slice = np.bincount(ss.slice_id, d, ss.n_slices) / np.maximum(ss.pixel_counts(), 1)
    assert np.mean(per_slice[twins] < 15.0) >= 0.9         # back on the stack's side
    assert not fit.twin[np.setdiff1d(rest, twins)].any()


def test_motion_poses_follow_a_smooth_motion_exactly():
    """Exact slice poses under a smooth motion over each stack (up to 8 deg / 3.6 mm about the brain's
    centre): the stage's motion model, expressed back in voxel indices (``motion_poses``), puts every
    pixel where the truth does (0.04 mm measured), while the stack's rigid pose leaves about 1 mm."""
    from tests.reconstruction.helpers import CENTRE, make_acquisition, pose_error_mm, rigid_about

    acq = make_acquisition(3, rot_deg=0.0, trans_mm=0.0)
    ss = acq.slice_set()
    n = np.bincount(ss.stack_index)[ss.stack_index].astype(float)
    phase = ss.slice_index / np.maximum(n - 1, 1)
    rotv = np.stack([8.0 * np.sin(np.pi * phase), 4.0 * np.cos(np.pi * phase), np.zeros_like(phase)], 1)
    shift = np.stack([3.0 * phase, np.zeros_like(phase), -2.0 * phase], 1)
    truth = rigid_about(CENTRE, rotv, shift) @ ss.atlas_from_voxel
    fit = fit_stack_rigid(ss, truth)
    assert pose_error_mm(ss, fit.motion_poses, truth) < 0.1
    assert pose_error_mm(ss, fit.stack_poses(ss), truth) > 0.5
    assert (fit.motion_mm > 1.0).all()                      # each stack says how far its motion moves it
    still = fit_stack_rigid(ss, ss.atlas_from_voxel)
    assert (still.motion_mm < 0.05).all()


def test_only_stacks_that_moved_more_than_the_threshold_follow_their_motion():
    """``coarse_align``'s stack bodies: a stack whose motion model moves its slices by more than the
    threshold is registered where that model puts them, the others as their rigid stack."""
    from service.reconstruction.coarse_to_fine import _bodies
    from tests.reconstruction.helpers import CENTRE, make_acquisition, rigid_about

    ss = make_acquisition(3, rot_deg=0.0, trans_mm=0.0).slice_set()
    n = np.bincount(ss.stack_index)[ss.stack_index].astype(float)
    phase = ss.slice_index / np.maximum(n - 1, 1)
    amount = np.array([1.0, 0.1, 0.0])[ss.stack_index][:, None]          # stack 0 moves, 1 barely, 2 not
    rotv = amount * np.stack([8.0 * np.sin(np.pi * phase), np.zeros_like(phase), np.zeros_like(phase)], 1)
    fit = fit_stack_rigid(ss, rigid_about(CENTRE, rotv, np.zeros_like(rotv)) @ ss.atlas_from_voxel)
    assert fit.motion_mm[0] > 1.0 > fit.motion_mm[1] and fit.motion_mm[2] < 0.05
    bodies = _bodies(ss, fit, 1.0)
    first = ss.stack_index == 0
    np.testing.assert_allclose(bodies[first], fit.motion_poses[first])
    np.testing.assert_allclose(bodies[~first], fit.stack_poses(ss)[~first])
    assert _bodies(ss, fit, np.inf) is None
    np.testing.assert_allclose(_bodies(ss, fit, 0.0)[~first & (ss.stack_index == 1)],
                               fit.motion_poses[ss.stack_index == 1])


def test_where_the_files_put_the_scanners_origin_changes_no_slices_place(acquisition):
    """Every stack file moved by one shift in scanner mm (the scanner's origin is the files' choice):
    the slices' places (``motion_poses``, atlas <- voxel) stay where they were, and each stack's
    ``atlas_from_scanner`` moves with the scanner frame; as well for a stack the stage cannot fit
    (its slices scattered 90 deg / 40 mm apart), which takes the mean of its slices about its centre."""
    from dataclasses import replace

    from service.geometry.pose import translate
    from tests.reconstruction.helpers import perturb

    ss = acquisition.slice_set()
    rng = np.random.default_rng(9)
    poses = perturb(ss.atlas_from_voxel, rng, 2.0, 2.0, ss.centres(ss.atlas_from_voxel))
    scattered = ss.stack_index == 2
    poses[scattered] = perturb(poses[scattered], rng, 90.0, 40.0, ss.centres(poses)[scattered])
    shift = np.array([200.0, 150.0, -100.0])
    moved = replace(ss, stack_affine=translate(shift) @ ss.stack_affine)
    here, there = fit_stack_rigid(ss, poses), fit_stack_rigid(moved, poses)
    assert not np.allclose(here.atlas_from_scanner[2], np.eye(4))          # the stage's fallback, not nothing
    np.testing.assert_allclose(there.motion_poses, here.motion_poses, atol=1e-5)
    np.testing.assert_allclose(there.atlas_from_scanner, here.atlas_from_scanner @ translate(-shift), atol=1e-5)
