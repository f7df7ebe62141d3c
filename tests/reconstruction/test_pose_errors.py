"""The refined poses' expected errors: each term of the model, and on a phantom whose volume is known,
a misplaced slice told from the placed ones by its NCC alone."""

from __future__ import annotations

import numpy as np

from service.reconstruction.grid import bounds_of, make_grid
from service.reconstruction.left_out import MIN_AREA_MM2, VolumeReference
from service.reconstruction.pose_errors import (
    BESIDE_MM,
    FRAME_MM,
    IN_VOLUME,
    LEFT_OUT,
    NCC_RATIO,
    PLACED_BY_STACK_MOTION,
    PLACED_BY_VOLUME,
    PREDICTED_SHARE,
    refined_expected_errors,
    roles,
)
from tests.reconstruction.helpers import make_acquisition, perturb, reference_on

LARGE, CAP = 2 * MIN_AREA_MM2, 0.5 * MIN_AREA_MM2


def errors(role, ncc, area=LARGE, predicted=4.0, held_out_ncc=0.92, framed=True):  # noqa: ANN001, ANN201
    """The model on arrays built from scalars or lists, with the placed slices' median NCC 0.9."""
    role = np.atleast_1d(role)
    n = len(role)
    full = lambda x: np.broadcast_to(np.asarray(x, np.float64), (n,)).copy()  # noqa: E731
    # four more slices in the volume at NCC 0.9 set the median the ratio is taken against
    out = refined_expected_errors(np.r_[role, [IN_VOLUME] * 4], np.r_[full(ncc), [0.9] * 4],
                                  np.r_[full(area), [LARGE] * 4], np.r_[full(predicted), [4.0] * 4],
                                  held_out_ncc=held_out_ncc, framed=framed)
    return out[:n]


def test_a_slice_in_the_volume_that_agrees_with_it_expects_the_frame_and_part_of_its_prediction() -> None:
    """... and a slice placed beside the volume the frame and its placement's error, whatever its
    prediction's (high: why the job left it out)."""
    got = errors(IN_VOLUME, 0.9, predicted=4.0)
    np.testing.assert_allclose(got, np.hypot(FRAME_MM, PREDICTED_SHARE * 4.0))
    assert got[0] < 4.0                                                   # the volume placed it better
    beside = errors([PLACED_BY_STACK_MOTION, PLACED_BY_VOLUME], 0.9, predicted=4.0)
    np.testing.assert_allclose(beside, np.hypot(FRAME_MM, BESIDE_MM))   # not in the volume: its own fit instead


def test_a_left_out_slice_keeps_at_least_its_starting_error_and_a_placed_one_needs_none() -> None:
    """A slice the job did not place keeps its starting pose's expected error, more where it
    disagrees with the volume (none known: none); a slice the volume placed has one without it (a
    client's poses carry none): the volume's."""
    got = errors([LEFT_OUT, LEFT_OUT, LEFT_OUT, IN_VOLUME], [0.2, 0.9, 0.9, 0.9], predicted=[9.0, 6.5, np.nan, np.nan])
    assert got[0] > 12.0 and got[1] == 6.5 and np.isnan(got[2]) and got[3] == FRAME_MM


def test_a_placed_slice_that_fits_the_volume_worse_expects_more_and_a_large_section_tells_more() -> None:
    ratios = np.array([NCC_RATIO, 0.9, 0.7, 0.4])
    large = errors([IN_VOLUME] * 4, 0.9 * ratios)
    cap = errors([IN_VOLUME] * 4, 0.9 * ratios, area=CAP)
    assert np.all(np.diff(large) > 0) and np.all(np.diff(cap[1:]) > 0)
    assert large[0] == cap[0] and np.all(large[1:] > cap[1:])
    assert large[-1] > 10.0                                               # far from where the volume says
    assert errors(IN_VOLUME, 0.99)[0] == errors(IN_VOLUME, 0.9)[0]       # above the ratio: agrees


def test_where_the_constants_do_not_hold_no_pose_is_surer_than_its_start() -> None:
    """Stacks that do not predict each other (leave-one-stack-out NCC 0.3), one stack (not
    measured) or no frame step: no slice's expected error falls below its starting pose's, and a
    slice without one has none."""
    coherent = errors([IN_VOLUME, PLACED_BY_VOLUME, IN_VOLUME], 0.9, predicted=[12.0, 3.0, np.nan], held_out_ncc=0.92)
    assert coherent[0] < 12.0 and coherent[1] == np.hypot(FRAME_MM, BESIDE_MM) and coherent[2] == FRAME_MM
    for kind in ({"held_out_ncc": 0.3}, {"held_out_ncc": None}, {"held_out_ncc": 0.92, "framed": False}):
        got = errors([IN_VOLUME, PLACED_BY_VOLUME, IN_VOLUME], 0.9, predicted=[12.0, 3.0, np.nan], **kind)
        assert got[0] == 12.0 and got[1] == 3.0 and np.isnan(got[2]), kind


def test_roles_put_a_slice_in_the_volume_before_its_left_out_flags() -> None:
    assert roles([True, False], [True, False], [False, False]).tolist() == [IN_VOLUME, LEFT_OUT]


def test_on_a_phantom_a_misplaced_slice_is_told_from_the_placed_ones() -> None:
    """Every slice at its true pose in the phantom's own volume but slice 8 of the first stack, 8 mm
    / 8 deg off (as a slice a job placed wrongly would be): its expected error rises past 5 mm, the
    others' stay at the frame's and their prediction's share."""
    acq = make_acquisition(0)
    every = acq.slice_set()
    grid = make_grid(1.0, bounds_of(every.positions(), 5.0))
    volume = VolumeReference(reference_on(grid, acq)[0].astype(np.float32), grid, every)
    poses = acq.true_poses.copy()
    off = (every.stack_index == 0) & (every.slice_index == 8)
    poses[off] = perturb(poses[off], np.random.default_rng(3), 8.0, 8.0, every.centres(poses)[off])
    got = refined_expected_errors(np.full(every.n_slices, IN_VOLUME), volume.ncc(poses), volume.areas_mm2,
                                  np.full(every.n_slices, 3.0), held_out_ncc=0.92)
    assert volume.areas_mm2[off][0] >= MIN_AREA_MM2
    assert got[off][0] > 5.0
    large = ~off & (volume.areas_mm2 >= MIN_AREA_MM2)
    np.testing.assert_allclose(got[large], np.hypot(FRAME_MM, PREDICTED_SHARE * 3.0))


def test_a_stack_the_others_do_not_predict_keeps_its_starting_errors_in_a_coherent_job() -> None:
    """A stack of another fetus in one job: the job's median passes, that stack's leave-out NCC (0.44)
    does not, and its few slices in the volume must not claim the volume's 2-3 mm."""
    role = np.full(4, IN_VOLUME)
    predicted = np.array([3.0, 3.0, 12.0, 15.0])
    common = dict(held_out_ncc=0.79)
    together = refined_expected_errors(role, np.full(4, 0.9), np.full(4, 1000.0), predicted, **common)
    assert (together < predicted).all()                                       # the volume vouches for them
    apart = refined_expected_errors(role, np.full(4, 0.9), np.full(4, 1000.0), predicted, **common,
                                    stack_held_out_ncc=np.array([0.86, 0.86, 0.44, 0.44]))
    np.testing.assert_allclose(apart[:2], together[:2])
    np.testing.assert_allclose(apart[2:], [12.0, 15.0])
