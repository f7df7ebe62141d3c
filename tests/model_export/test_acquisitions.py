"""Simulated acquisitions: exact truth, and the pipeline with a twin-confused estimator, per motion level."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from model_export.acquisitions import interleaved_times, simulate_acquisition
from model_export.evaluate_acquisitions import NoisyTwinEstimator, evaluate_acquisitions, markdown
from service.geometry import sampling
from service.geometry.pose import apply
from tests.api.conftest import INFO
from tests.support.phantoms import phantom_brain

BRAIN = phantom_brain(0)


@pytest.mark.parametrize(("motion", "turned"), [("moderate", False), ("jumps", False), ("independent", False),
                                               ("moderate", True)])
def test_every_voxel_shows_the_atlas_at_its_true_position(motion: str, turned: bool) -> None:
    """The simulated truth composes the motion about the brain centre with the stack's geometry: every
    voxel shows the atlas where its ``atlas_from_voxel`` says, smooth, jumping and independent motion
    alike, and for stacks given axes of their own (``turned``: each slice's true normal is its axes')."""
    img, mask, aff = BRAIN
    axes = [Rotation.random(random_state=k).as_matrix() for k in range(3)] if turned else None
    stacks = simulate_acquisition(img, mask, aff, np.random.default_rng(0), motion, axes=axes, size=48, pixel_mm=2.0,
                                  thickness_mm=0.0, noise=0.0, bias=0.0)
    for s, a in zip(stacks, axes or [None] * 3):
        normals = s.atlas_from_voxel[:, :3, 2] / np.linalg.norm(s.atlas_from_voxel[:, :3, 2], axis=1, keepdims=True)
        if a is not None:                                  # within the moderate motion's 20 deg
            assert np.all(np.abs(normals @ a[:, 2]) > np.cos(np.radians(21.0)))
    for s in stacks:
        n = s.volume.array.shape[2]
        ij = np.stack(np.meshgrid(np.arange(48), np.arange(48), indexing="ij"), -1).reshape(-1, 2)
        for k in (n // 3, n // 2):
            vox = np.concatenate([ij, np.full((len(ij), 1), k)], 1).astype(float)
            want = sampling.sample_points(img, aff, apply(s.atlas_from_voxel[k], vox))
            got = s.volume.array[ij[:, 0], ij[:, 1], k]
            assert np.abs(got - want).max() < 1e-3 * img.max()
            assert want.max() > 0.2 * img.max()


def test_pipeline_with_a_twin_confused_estimator_per_motion_level(tmp_path) -> None:  # noqa: ANN001
    img, mask, aff = BRAIN
    vol = type("V", (), {"image": img, "mask": mask, "affine": aff})
    est = NoisyTwinEstimator(INFO, np.random.default_rng(1))
    said: list[str] = []
    out = evaluate_acquisitions([vol], est, np.random.default_rng(2), ("mild", "moderate", "extreme"), per_volume=2, mc_samples=20,
                                bias_correction=False, told=("interleaved",), size=64, pixel_mm=1.6,
                                slices=tmp_path / "slices.npz", progress=said.append)
    assert [line.split(" (")[0] for line in said] == [f"{level}: acquisition {k} of 6" for k, level in
                                                    enumerate(["mild"] * 2 + ["moderate"] * 2 + ["extreme"] * 2, 1)]
    for level in ("mild", "moderate"):
        s = out[level]
        # >= 99 % is the target on the validation volumes (model_export/reports/acquisitions.md); this
        # small phantom has fewer slices per stack, and 1-2 sagittal slices next to each other in time,
        # both given on the twin, can carry a short motion kernel with them.
        assert s["right_branch"] >= 0.97, (level, s)
        assert s["ed"]["mean"] < s["ed_network_min"]["mean"], (level, s)       # the stack fit beats the slices
        assert s["decidable_stacks"] == 1.0
        assert 0.5 < s["ed_rms"] / s["expected_error_mm_rms"] < 2.0, (level, s)   # the expected error is honest
        assert 0 < s["components"]["tilt_deg"] < 90 and s["components"]["off_plane_mm"] <= s["components"]["centre_mm"]
        assert set(s["ed_by_depth"]) == {"centre", "middle", "outer"} and np.isfinite(list(s["ed_by_time"].values())).all()
        told = out[f"{level}, told interleaved"]                 # the same network poses, the stage told the order
        assert told["ed_network"] == s["ed_network"] and told["right_branch"] >= 0.97, (level, told)
    with np.load(tmp_path / "slices.npz") as cols:          # every slice of every row, as the summary saw it
        for row in out:
            keep = cols[f"{row}/mask_pixels"] >= 20
            assert keep.sum() == out[row]["slices"] and cols[f"{row}/ed"][keep].mean() == out[row]["ed"]["mean"]
            assert len(np.unique(cols[f"{row}/stack"])) == 3 * 2                  # 3 stacks x 2 acquisitions
            assert np.all(cols[f"{row}/moved_mm"][keep] >= 0)
            # a slice with nothing in it has no network pose to have moved from (the estimator skips it)
            assert np.isnan(cols[f"{row}/moved_mm"][cols[f"{row}/mask_pixels"] == 0]).all()
        motion = {lv: np.median(cols[f"{lv}/motion_mm"]) for lv in ("mild", "moderate", "extreme")}
        assert 0 < motion["mild"] < motion["moderate"] < motion["extreme"], motion
        fitted = {lv: np.median(cols[f"{lv}/fitted_motion_mm"]) for lv in ("mild", "moderate")}
        assert fitted["mild"] < fitted["moderate"] < 2 * motion["moderate"], (fitted, motion)
        assert np.isnan(cols["extreme/fitted_motion_mm"]).all()                    # undecidable: no rigid fit
        # what the service knows of each slice: the image refinement ran at mild motion, not at extreme
        checked = np.isfinite(cols["mild/mismatch"])
        assert checked.mean() > 0.5 and 0.5 < np.nanmedian(cols["mild/mismatch"]) < 2.0   # over each request's median
        assert np.all(cols["mild/expected_stage"][checked] > 0)
        assert np.isnan(cols["extreme/mismatch"]).all() and np.isnan(cols["extreme/expected_stage"]).all()
        assert np.all(cols["mild/spread"][checked] > 0) and np.isnan(cols["extreme/spread"]).all()   # the Laplace spread
        assert np.all((cols["mild/twin_mass"] >= 0) & (cols["mild/twin_mass"] <= 1))
    report = markdown(out, "phantom")
    assert report.count("| mild, told interleaved |") == 2 and "along the normal" in report
    ex = out["extreme"]
    assert ex["decidable_stacks"] == 0.0
    assert ex["ed_min"]["mean"] == ex["ed_network_min"]["mean"]                  # no slice made worse


def test_true_motion_is_the_distance_from_the_stacks_mean_rigid_placement() -> None:
    """A stack whose slices share one placement has no motion; when one slice of six turns about its
    own centre, it carries most of the turn and the others only the mean's small share."""
    from model_export.evaluate_acquisitions import true_motion_mm
    from service.geometry import anchors, se3

    rng = np.random.default_rng(3)
    scanner_from_voxel = np.diag([0.8, 0.8, 3.0, 1.0])
    atlas_from_scanner = se3.exp(np.r_[rng.normal(size=3) * 0.3, rng.normal(size=3) * 5.0])
    voxel_from_network = np.stack([np.eye(4)] * 6)
    voxel_from_network[:, 2, 3] = np.arange(6)
    poses = atlas_from_scanner @ scanner_from_voxel @ voxel_from_network          # network frame -> atlas
    atlas_from_voxel = np.stack([atlas_from_scanner @ scanner_from_voxel] * 6)
    np.testing.assert_allclose(true_motion_mm(atlas_from_voxel, scanner_from_voxel, poses), 0.0, atol=1e-9)
    turn = poses[2] @ se3.exp(np.r_[np.deg2rad(6.0), 0.0, 0.0, 0.0, 0.0, 0.0]) @ np.linalg.inv(poses[2])
    moved = poses.copy()
    moved[2] = turn @ poses[2]
    moved_voxel = atlas_from_voxel.copy()
    moved_voxel[2] = turn @ atlas_from_voxel[2]
    got = true_motion_mm(moved_voxel, scanner_from_voxel, moved)
    whole = anchors.ed(moved[2:3], poses[2:3])[0]                       # the turn itself, at the anchors
    assert whole > 3.0
    assert 0.75 * whole < got[2] < whole                                # less the mean's share (about 1/6)
    assert np.all(got[[0, 1, 3, 4, 5]] < 0.3 * whole), (got, whole)


def test_the_stages_rigid_placement_is_the_stacks_true_mean_placement() -> None:
    """With nearly exact network poses (1 deg / 1 mm, either twin), each stack's reported rigid
    placement, composed with the file's geometry and the service's crop, lands every slice where the
    stack's true mean placement puts it: the composition behind ``fitted_motion_mm``."""
    from model_export.evaluate_acquisitions import rigid_poses, run_acquisition
    from service.pipeline.documents import stack_objects
    from service.geometry import anchors, se3, twin

    img, mask, aff = BRAIN
    stacks = simulate_acquisition(img, mask, aff, np.random.default_rng(4), "mild", size=64, pixel_mm=1.6)
    est = NoisyTwinEstimator(INFO, np.random.default_rng(5), noise_deg=1.0, noise_mm=1.0, other_twin_fraction=0.0)
    (predictions,), prepared, truth = run_acquisition(stacks, est, mc_samples=20, bias_correction=False)
    for res, p, sim, true in zip(stack_objects(predictions), prepared, stacks, truth):
        rigid = rigid_poses(res["consistency"], sim.volume.affine, np.linalg.inv(p.network_from_voxel()))
        assert rigid is not None
        atlas_from_scanner = sim.atlas_from_voxel @ np.linalg.inv(sim.volume.affine)
        still = se3.frechet_mean(atlas_from_scanner) @ sim.volume.affine @ np.linalg.inv(p.network_from_voxel())
        np.testing.assert_allclose(still, se3.frechet_mean(atlas_from_scanner) @ np.linalg.inv(atlas_from_scanner) @ true,
                                   atol=1e-6)                                    # the same placement, two ways
        err = np.minimum(anchors.ed(rigid, still), anchors.ed(rigid, twin.twin(still, INFO.symmetry_plane_x_mm)))
        assert np.median(err) < 1.0, (sim.orientation, err)         # the slices themselves move ~3 mm (mild)


def test_each_slices_twin_distance_is_that_of_its_returned_pose() -> None:
    """``twin_mm`` is the distance of the pose the service returns to its own twin: within twice that
    pose's E.D. of its true pose's distance to its twin (the mirror keeps anchor-point distances),
    which the network's own poses (10 deg / 10 mm off, before the stage) are not."""
    from model_export.evaluate_acquisitions import Scored, run_acquisition, score
    from service.geometry import twin

    img, mask, aff = BRAIN
    stacks = simulate_acquisition(img, mask, aff, np.random.default_rng(4), "mild", size=64, pixel_mm=1.6)
    est = NoisyTwinEstimator(INFO, np.random.default_rng(5), other_twin_fraction=0.0)
    (predictions,), prepared, truth = run_acquisition(stacks, est, mc_samples=20, bias_correction=False)
    sc = Scored()
    score(predictions, prepared, truth, stacks, INFO.symmetry_plane_x_mm, sc)
    true_twin = np.concatenate([twin.twin_distance_mm(t, INFO.symmetry_plane_x_mm) for t in truth])
    gap, e = np.abs(sc.array("twin_mm") - true_twin), sc.array("ed")
    assert np.all(gap <= 2 * e + 1e-6)
    assert true_twin.min() < 20.0 < 60.0 < true_twin.max()          # slices near the plane and far from it


def test_jumps_are_few_sudden_moves_and_independent_slices_stay_in_their_bounds() -> None:
    """``jumps``: ordered by acquisition, the trajectory is smooth drift (small steps) with 1 to
    MAX_JUMPS steps far larger than the drift's; ``independent``: every slice within 20 deg and 8 mm per
    axis, and neighbours in time no closer than any two slices."""
    from model_export.acquisitions import JUMP_DEG, JUMP_MM, MAX_JUMPS, motion_twists
    from service.geometry import se3

    rng = np.random.default_rng(3)
    times = interleaved_times(30)
    for _ in range(20):
        tw = motion_twists(times, rng, "jumps")[np.argsort(times)]
        steps = se3.exp(tw[1:]) @ se3.inverse(se3.exp(tw[:-1]))
        size = np.linalg.norm(se3.log(steps), axis=1)
        drift = np.median(size)
        assert 1 <= (size > 5 * drift).sum() <= MAX_JUMPS, size.round(3)
    tw = motion_twists(times, rng, "independent")
    assert np.degrees(np.linalg.norm(tw[:, :3], axis=1)).max() <= JUMP_DEG + 1e-9
    assert np.abs(tw[:, 3:]).max() <= JUMP_MM and np.abs(tw[:, 3:]).max() > JUMP_MM / 2
    ordered = tw[np.argsort(times)]
    assert np.linalg.norm(np.diff(ordered, axis=0), axis=1).mean() > 0.8 * np.linalg.norm(tw - tw.mean(0), axis=1).mean()
