"""The left-right twin: rendered equal from a symmetric phantom, compositions, labels, the plane fit."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import anchors, encodings, iterators, sampling, se3, twin
from service.geometry.pose import apply, make_pose
from service.io.volume import Volume
from service.preprocess.stack import split_stack
from tests.support.phantoms import mirror_symmetric_volume

PLANE_X = 1.5


def test_twin_is_a_proper_involution_and_mirrors_plane_points() -> None:
    rng = np.random.default_rng(0)
    poses = iterators.random_poses(50, rng, tz_max_mm=20.0, centre=np.zeros(3))
    tw = twin.twin(poses, PLANE_X)
    assert np.allclose(np.linalg.det(tw[:, :3, :3]), 1.0)
    assert np.allclose(tw[:, :3, :3].transpose(0, 2, 1) @ tw[:, :3, :3], np.eye(3), atol=1e-12)
    assert np.allclose(twin.twin(tw, PLANE_X), poses)
    plane_pts = np.concatenate([rng.uniform(-50, 50, (7, 2)), np.zeros((7, 1))], axis=1)
    got = apply(tw[:, None], plane_pts[None])
    want = twin.mirror_points(apply(poses[:, None], plane_pts[None]), PLANE_X)
    assert np.allclose(got, want)
    # off the plane the twin is NOT the mirror: the normal is reversed
    off = apply(tw, np.array([0.0, 0.0, 1.0]))
    assert np.allclose(off, twin.mirror_points(apply(poses, np.array([0.0, 0.0, -1.0])), PLANE_X))


def test_slice_and_twin_render_the_same_image_from_a_symmetric_phantom() -> None:
    vol, aff = mirror_symmetric_volume(PLANE_X)
    rng = np.random.default_rng(1)
    poses = iterators.random_poses(20, rng, tz_max_mm=10.0, centre=np.array([PLANE_X, 0.0, 0.0]))
    a = sampling.sample_slices(vol, aff, poses, size=32, pixel_mm=1.0, thickness_mm=3.0)
    b = sampling.sample_slices(vol, aff, twin.twin(poses, PLANE_X), size=32, pixel_mm=1.0, thickness_mm=3.0)
    assert np.abs(a).max() > 0.3
    assert np.abs(a - b).max() < 1e-4 * np.abs(a).max()
    # and the renderer does see a mirror about a wrong plane
    c = sampling.sample_slices(vol, aff, twin.twin(poses, PLANE_X + 4.0), size=32, pixel_mm=1.0, thickness_mm=3.0)
    assert np.abs(a - c).max() > 0.05


def test_twin_cases_named_in_the_design() -> None:
    axial = make_pose(np.eye(3), [5.0, 2.0, 3.0])
    tw = twin.twin(axial, 0.0)
    assert np.allclose(tw[:3, :3], np.diag([-1.0, 1.0, -1.0]))     # 180 deg about the in-plane y axis
    assert np.allclose(tw[:3, 3], [-5.0, 2.0, 3.0])
    sag_rot = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])   # x->A, y->S, normal R
    sag = make_pose(sag_rot, [12.0, 1.0, 2.0])
    tw = twin.twin(sag, 0.0)
    assert np.allclose(tw[:3, :3], sag_rot)                          # same orientation ...
    assert np.allclose(tw[:3, 3], [-12.0, 1.0, 2.0])                 # ... at the mirrored position
    assert np.degrees(np.linalg.norm(se3.so3_log(tw[:3, :3].T @ axial[:3, :3]))) > 0  # sanity


@pytest.mark.parametrize("label_type", [*encodings.LABEL_TYPES])
def test_twin_label_matches_the_twin_pose_for_every_label_type(label_type: str) -> None:
    rng = np.random.default_rng(2)
    poses = iterators.random_poses(30, rng, tz_max_mm=20.0, centre=np.array([3.0, -2.0, 5.0]))
    lab = encodings.encode(label_type, poses)
    got = encodings.decode(label_type, twin.twin_label(label_type, lab, PLANE_X))
    assert np.allclose(got, twin.twin(poses, PLANE_X), atol=1e-9)


def test_twin_of_anchor_label_is_x_mirror_even_for_non_rigid_predictions() -> None:
    lab = np.arange(9.0)[None] * 3.0 - 7.0
    tw = twin.twin_label("anchor", lab, 2.0).reshape(3, 3)
    assert np.allclose(tw[:, 0], 4.0 - lab.reshape(3, 3)[:, 0])
    assert np.allclose(tw[:, 1:], lab.reshape(3, 3)[:, 1:])
    assert np.allclose(anchors.decode(twin.twin_label("anchor", anchors.encode(np.eye(4)), 0.0)),
                       twin.twin(np.eye(4), 0.0))


def test_atlas_from_voxel_of_the_twin_places_each_voxel_at_its_mirror() -> None:
    """The service's composition ``pose @ network_from_voxel`` under the twin, on a real stack split."""
    rng = np.random.default_rng(4)
    aff = np.array([[0.0, 0.9, 0.1, -40.0], [-1.1, 0.0, 0.0, 30.0], [0.0, -0.05, 3.0, -20.0], [0, 0, 0, 1.0]])
    vol = Volume(np.zeros((24, 20, 6), np.float32), aff)
    slices = split_stack(vol, np.ones(vol.array.shape, bool))
    centroid = np.array([1.5, -2.0, 0.0])
    network_from_voxel = se3.inverse(make_pose(np.eye(3), centroid)) @ slices.slice_from_voxel  # [6,4,4]
    poses = iterators.random_poses(6, rng, tz_max_mm=15.0, centre=np.zeros(3))
    k = np.arange(6.0)
    ij = rng.uniform(0, 19, (6, 5, 2))
    vox = np.concatenate([ij, np.broadcast_to(k[:, None, None], (6, 5, 1))], -1)   # (i, j, k) of slice k
    plain = apply((poses @ network_from_voxel)[:, None], vox)
    twinned = apply((twin.twin(poses, PLANE_X) @ network_from_voxel)[:, None], vox)
    assert np.allclose(twinned, twin.mirror_points(plain, PLANE_X), atol=1e-9)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_measure_plane_x_recovers_the_plane_of_a_phantom(sign: float) -> None:
    vol, aff = mirror_symmetric_volume(plane_x=2.4)
    if sign < 0:                                   # store the x axis reversed (radiological order)
        vol = vol[::-1].copy()
        aff = aff @ np.array([[-1.0, 0, 0, vol.shape[0] - 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    vol = np.roll(vol, 3, axis=0)                  # off-centre in its grid ...
    aff = aff.copy()
    aff[0, 3] -= 3.0 * aff[0, 0]                   # ... with the affine following it
    assert twin.measure_plane_x(vol, aff) == pytest.approx(2.4, abs=0.1)


def test_measure_plane_x_refuses_an_oblique_grid() -> None:
    aff = np.eye(4)
    aff[:3, :3] = se3.so3_exp(np.array([0.0, 0.0, 0.3]))
    with pytest.raises(ValueError, match="not aligned"):
        twin.measure_plane_x(np.zeros((8, 8, 8)), aff)


def test_twin_distance_is_the_ed_to_the_twin_and_grows_off_the_plane() -> None:
    """A pose's distance to its twin is its E.D. to it, the same seen from the twin; a sagittal slice
    ``s`` mm off the plane is ``2 s`` from its twin (the same orientation, mirrored position)."""
    rng = np.random.default_rng(5)
    poses = se3.exp(np.concatenate([rng.normal(scale=1.0, size=(20, 3)), rng.normal(scale=20.0, size=(20, 3))], 1))
    d = twin.twin_distance_mm(poses, PLANE_X)
    np.testing.assert_allclose(d, anchors.ed(poses, twin.twin(poses, PLANE_X)))
    np.testing.assert_allclose(twin.twin_distance_mm(twin.twin(poses, PLANE_X), PLANE_X), d, atol=1e-9)
    sagittal = np.stack([make_pose(np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), [PLANE_X + s, 4.0, -7.0])
                         for s in (0.0, 3.0, -10.0)])
    np.testing.assert_allclose(twin.twin_distance_mm(sagittal, PLANE_X), [0.0, 6.0, 20.0], atol=1e-9)


def test_twin_risk_falls_with_the_distance_and_is_the_logistic() -> None:
    d = np.array([0.0, 5.0, 20.0, 80.0])
    p = twin.twin_risk(d, (-1.2, -0.13))
    assert np.all(np.diff(p) < 0) and p[-1] < 1e-4
    np.testing.assert_allclose(np.log(p / (1 - p)), -1.2 - 0.13 * d)


@pytest.mark.parametrize("n", [2, 4, 6])
def test_an_even_split_between_the_twins_is_mirrored_with_the_slice(n: int) -> None:
    """Half the MC samples on each twin: the branch followed the medoid, chosen among equal sums by
    rounding (with the plane off x = 0, 2 x0 - x), so a slice and its mirror twin could answer on the
    same branch. Now the first sample's branch is kept, which the mirror carries over."""
    rng = np.random.default_rng(7)
    plane = 1.2
    for _ in range(50):
        base = se3.exp(np.concatenate([rng.normal(0, 0.6, 3), rng.normal(0, 20, 3)]))
        x = base @ se3.exp(rng.normal(0, 0.05, (n, 6)))
        x[n // 2:] = twin.twin(x[n // 2:], plane)                       # an exact 50/50 split
        aligned, flipped = twin.align_samples(x, plane)
        mirrored, flipped_m = twin.align_samples(twin.twin(x, plane), plane)
        np.testing.assert_allclose(mirrored, twin.twin(aligned, plane), atol=1e-9)
        assert not flipped[0] and not flipped_m[0] and flipped.sum() == n // 2
