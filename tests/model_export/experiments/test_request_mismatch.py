"""The request-mismatch experiment's judging: a request's expected errors grown by its remaining image
mismatch change the accept flags of that request alone, as the rule says."""

from __future__ import annotations

import numpy as np

from model_export.experiments.request_mismatch import Request, factor, judged


def _request(after: float, ed_mm: list[float], expected_mm: list[float]) -> Request:
    return Request("cache", "moderate", 5.0, after, np.array(ed_mm), np.ones(len(ed_mm), bool), np.array(expected_mm))


def test_the_factor_grows_in_proportion_past_its_reference_and_never_shrinks() -> None:
    assert factor(0.1, 0.5, 1.0) == 1.0 and factor(0.5, 0.5, 1.0) == 1.0
    assert np.isclose(factor(1.5, 0.5, 1.0), 3.0) and np.isclose(factor(2.0, 0.5, 0.5), 2.0)


def test_only_the_request_whose_images_disagree_loses_its_accepted_slices() -> None:
    """Two requests with the same slices and expected errors: the one whose remaining mismatch is 4 x
    the reference has every expected error grown 4 x (past the limit), the other keeps its flags."""
    clean = _request(0.1, [2.0, 3.0, 12.0], [2.0, 2.0, 2.0])
    disagreeing = _request(2.0, [2.0, 3.0, 12.0], [2.0, 2.0, 2.0])
    as_is = judged([clean, disagreeing], 4.8, None, 1.0)
    grown = judged([clean, disagreeing], 4.8, 0.5, 1.0)
    assert as_is["good_accepted"] == 1.0 and as_is["bad_accepted"] == 1.0 and as_is["bad_slices"] == 2
    assert grown["good_accepted"] == 0.5 and grown["bad_accepted"] == 0.5
    assert judged([clean], 4.8, 0.5, 1.0) == judged([clean], 4.8, None, 1.0)


def test_the_rms_ratio_compares_errors_with_the_grown_expectations() -> None:
    r = _request(1.0, [4.0, 4.0], [2.0, 2.0])
    assert np.isclose(judged([r], 4.8, None, 1.0)["rms_ratio"], 2.0)
    assert np.isclose(judged([r], 4.8, 0.5, 1.0)["rms_ratio"], 1.0)


def test_the_image_term_at_given_poses_is_lowest_at_the_truth() -> None:
    """``mismatch_at`` measures the image stage's term where the poses are: at a phantom acquisition's
    true poses it is lower than at poses moved by a few degrees and millimetres, and the stage's
    further refinement from the moved poses brings it down again."""
    from model_export.acquisitions import simulate_acquisition
    from model_export.evaluate_acquisitions import prepare_acquisition
    from model_export.experiments.request_mismatch import mismatch_at
    from tests.api.conftest import INFO
    from tests.consistency.conftest import disturbed
    from tests.support.phantoms import phantom_brain

    img, mask, aff = phantom_brain(0)
    stacks = simulate_acquisition(img, mask, aff, np.random.default_rng(3), "mild", size=64, pixel_mm=1.6)
    prepared, truth = prepare_acquisition(stacks, INFO, bias_correction=False)
    active = [np.ones(len(t), bool) for t in truth]
    at_truth, _ = mismatch_at(prepared, active, truth)
    moved, refined = mismatch_at(prepared, active, disturbed(truth, 3.0, 2.0, seed=1))
    assert at_truth < 0.5 * moved
    assert refined < 0.6 * moved
