"""Pose accuracy against the truth of a generated whole-uterus scene: the scene's true slice poses,
the service's answer and the twin meet in one frame."""

from __future__ import annotations

import numpy as np
import pytest

from model_export.evaluate_acquisitions import NoisyTwinEstimator
from model_export.localiser.pose_accuracy import _upload, score_scene
from model_export.localiser.scenes import HeadModel, synth_scene
from tests.api.conftest import INFO
from tests.support.phantoms import phantom_brain


@pytest.fixture(scope="module")
def scene():  # noqa: ANN201
    image, mask, affine = phantom_brain(3)
    affine = affine.copy()
    affine[:3, 3] = [-40.0, 25.0, 7.0]
    return synth_scene(HeadModel.from_arrays(image, mask, affine), np.random.default_rng(5), "heldout",
                       random_contrast=False, rigid=True)


def test_an_estimator_that_answers_the_truth_or_its_twin_scores_zero_twin_min(scene) -> None:  # noqa: ANN001
    """Each slice's network answer is its true pose or its left-right twin, without noise: the scored
    slices are then at 0 mm twin-min (but those the stack stage re-places as outliers: 3 of 28 in this
    scene), and at 0 mm or further against the truth."""
    estimator = NoisyTwinEstimator(INFO, np.random.default_rng(0), noise_deg=0.0, noise_mm=0.0, other_twin_fraction=0.0)
    got = score_scene(scene, "brain", estimator, mc_samples=4)
    posed = np.isfinite(got["ed"])
    assert posed.sum() >= 5
    assert np.mean(got["ed_min"][posed] < 0.01) >= 0.85, got["ed_min"]
    assert np.all(got["ed"][posed] >= got["ed_min"][posed] - 1e-9)


def test_a_moved_answer_is_scored_by_how_far_it_moved(scene) -> None:  # noqa: ANN001
    """The same estimator told a truth 5 mm off along x: every scored slice's E.D. is about 5 mm."""
    class Shifted(NoisyTwinEstimator):
        def estimate(self, inputs, mc_samples):  # noqa: ANN001, ANN202
            shift = np.eye(4)
            shift[0, 3] = 5.0
            self.truth = shift @ self.truth
            return super().estimate(inputs, mc_samples)

    estimator = Shifted(INFO, np.random.default_rng(0), noise_deg=0.0, noise_mm=0.0, other_twin_fraction=0.0)
    got = score_scene(scene, "brain", estimator, mc_samples=4)
    assert 3.0 < np.nanmedian(got["ed_min"]) < 7.0, got["ed_min"]


def test_a_mask_drawn_to_the_skull_s_outer_edge_holds_the_skull_s_inside_and_says_it_holds_csf(scene) -> None:  # noqa: ANN001
    """``skull-csf+G``: the skull's inside grown by G mm, sent with ``masks_hold_csf`` (the pipeline
    insets it again); ``skull`` is sent as it is."""
    inside, outer = _upload(scene, "skull"), _upload(scene, "skull-csf+3")
    small, large = inside.mask.array > 0, outer.mask.array > 0
    assert outer.mask_holds_csf and not inside.mask_holds_csf
    assert np.all(large[small]) and large.sum() > 1.2 * small.sum()


def test_a_case_s_stacks_sent_together_place_one_head_in_one_frame(scene) -> None:  # noqa: ANN001
    """Three stacks of one head, each in its own orientation and surroundings with the first's look
    (contrast and head layers), placed in one scanner frame: every slice's truth maps to one scanner
    pose of the head (up to its motion), and an estimator that answers the truth keeps the stacks
    sent together within a millimetre of it (stacks drawn each with its own CSF and skull, which no
    one head has, pull each other's slices by 1.1 mm)."""
    from model_export.localiser.pose_accuracy import in_one_frame

    image, mask, affine = phantom_brain(3)
    head = HeadModel.from_arrays(image, mask, affine)
    first = synth_scene(head, np.random.default_rng(20), "heldout", random_contrast=False, rigid=True, motion="mild")
    scenes = in_one_frame([first] + [synth_scene(head, np.random.default_rng(20 + k), "heldout", random_contrast=False,
                                                 rigid=True, motion="mild", look=first.look) for k in (1, 2)],
                          np.random.default_rng(9))
    assert scenes[1].look == scenes[2].look == first.look and first.look.layers is not None
    scanner_from_atlas = [s.volume.affine @ np.linalg.inv(s.atlas_from_voxel[len(s.atlas_from_voxel) // 2])
                          for s in scenes]
    assert np.allclose(scanner_from_atlas[0], scanner_from_atlas[1]) and np.allclose(scanner_from_atlas[0],
                                                                                     scanner_from_atlas[2])
    assert not np.allclose(scenes[0].volume.affine[:3, :3], scenes[1].volume.affine[:3, :3])
    estimator = NoisyTwinEstimator(INFO, np.random.default_rng(0), noise_deg=0.0, noise_mm=0.0, other_twin_fraction=0.0)
    got = score_scene(scenes, "brain", estimator, mc_samples=4)
    posed = np.isfinite(got["ed"])
    assert len(got["ed"]) == len(got["poses"]) and posed.sum() >= 15
    assert np.median(got["ed_min"][posed]) < 0.8, got["ed_min"]


def test_an_unknown_planning_of_the_stacks_is_refused_before_any_scene_is_drawn() -> None:
    """``planning`` is one of :data:`PLANNINGS`; another is refused by name (no atlas is read)."""
    from model_export.localiser.pose_accuracy import PLANNINGS, validation_cases

    assert PLANNINGS == ("independent", "orthogonal")
    with pytest.raises(ValueError, match="planning"):
        validation_cases(1, stacks=3, planning="diagonal", root="/nonexistent")
