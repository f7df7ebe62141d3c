"""Intensity matching across stacks: the fitted fields, and what they do to the image refinement."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import service.consistency.image_refinement as image_refinement
from service.consistency.image_refinement import MIN_LINE_WEIGHT, refine
from service.consistency.intensity_match import SLOPE_SCALE_MM, Fields, fit_fields, matched, slice_basis
from service.consistency.intersections import ImageTerm, candidate_pairs
from service.consistency.slice_images import SampledStack
from service.geometry import se3
from service.geometry.anchors import ed
from tests.consistency.conftest import disturbed

# Three stacks of ten slices; per stack: gain, odd-even step, two in-plane slopes (log units)
TRUE = np.array([[0.0, 0.0, 0.0, 0.0],
                 [0.15, 0.12, 0.3, -0.2],
                 [-0.1, -0.1, -0.25, 0.1]])


def _points(rng: np.random.Generator, count: int = 6000) -> tuple:
    """``count`` points on lines between slices of different stacks: each point's slice and stack per
    role, in-plane places, the request's slice basis and the anatomy each point shows."""
    stack = np.stack([rng.integers(0, 3, count), rng.integers(0, 3, count)])
    stack[1] = np.where(stack[1] == stack[0], (stack[0] + 1) % 3, stack[1])           # different stacks
    local = rng.integers(0, 10, (2, count))
    slices = 10 * stack + local
    u = rng.uniform(-0.4, 0.4, (2, count, 2))
    basis = slice_basis(np.tile(np.arange(10), 3))
    return slices, stack, u, basis, rng.uniform(0.5, 1.5, count)


def _observed(anatomy: np.ndarray, slices: np.ndarray, stack: np.ndarray, u: np.ndarray, basis: np.ndarray,
              coefficients: np.ndarray) -> np.ndarray:
    field = Fields(coefficients, 0)
    return np.stack([anatomy * np.exp([field.log_field(s, basis[g], x) for s, g, x in zip(stack[r], slices[r], u[r])])
                     for r in (0, 1)])


def test_fit_recovers_each_stacks_gain_step_and_slope_relative_to_the_others() -> None:
    """Only differences between stacks are seen: the fit returns the fields up to one field common to
    all stacks, and here the first stack's is none, so the others' come back as drawn."""
    rng = np.random.default_rng(0)
    slices, stack, u, basis, anatomy = _points(rng)
    values = _observed(anatomy, slices, stack, u, basis, TRUE)
    fitted = fit_fields(values, np.ones(len(anatomy)), slices, stack, u, basis, 3).coefficients
    relative = fitted - fitted[0]
    assert np.abs(relative - TRUE).max() < 0.02, relative.round(3)


def test_points_that_show_other_tissue_do_not_set_the_fields() -> None:
    """A fifth of the points read tissue off by a factor of 2-3 (lines seen at wrong poses): the
    robust loss keeps the fields within a few percent of the others' answer."""
    rng = np.random.default_rng(1)
    slices, stack, u, basis, anatomy = _points(rng)
    values = _observed(anatomy, slices, stack, u, basis, TRUE)
    wrong = rng.random(len(anatomy)) < 0.2
    values[0, wrong] *= rng.choice([0.4, 2.5], wrong.sum())
    fitted = fit_fields(values, np.ones(len(anatomy)), slices, stack, u, basis, 3).coefficients
    assert np.abs(fitted - fitted[0] - TRUE)[:, :2].max() < 0.05, (fitted - fitted[0]).round(3)


def test_a_value_that_is_not_finite_takes_no_part() -> None:
    rng = np.random.default_rng(2)
    slices, stack, u, basis, anatomy = _points(rng)
    values = _observed(anatomy, slices, stack, u, basis, TRUE)
    values[0, :5], values[1, 5:10] = np.inf, np.nan
    fitted = fit_fields(values, np.ones(len(anatomy)), slices, stack, u, basis, 3)
    assert fitted.points == len(anatomy) - 10
    assert np.abs(fitted.coefficients - fitted.coefficients[0] - TRUE).max() < 0.02


def test_without_points_nothing_is_changed() -> None:
    fields = fit_fields(np.zeros((2, 0)), np.zeros(0), np.zeros((2, 0), int), np.zeros((2, 0), int),
                        np.zeros((2, 0, 2)), slice_basis(np.arange(4)), 2)
    assert fields.points == 0 and not fields.coefficients.any()
    assert np.array_equal(fields.stack_field(1, 4, (3, 5), (1.0, 1.0)), np.ones((4, 3, 5), np.float32))


@pytest.fixture(scope="module")
def shaded(acquisition):  # noqa: ANN001
    """The phantom acquisition with its second stack's odd slices 30 % brighter than its even ones
    and a fall-off of 1.6 x across it, and its third stack 25 % darker and falling off down its rows."""
    images, truth = acquisition
    second, third = images[1], images[2]
    n, h, w = second.images.shape
    ramp = np.exp(np.linspace(-0.25, 0.25, w))[None, None, :]
    step = np.where(np.arange(n) % 2 == 1, 1.3, 1.0)[:, None, None]
    fall = 0.75 * np.exp(np.linspace(0.2, -0.2, third.images.shape[1]))[None, :, None]
    return [images[0], replace(second, images=(second.images * step * ramp).astype(np.float32)),
            replace(third, images=(third.images * fall).astype(np.float32))], truth


def _refined_error(images, truth, match: bool, monkeypatch) -> float:  # noqa: ANN001
    monkeypatch.setattr(image_refinement, "MATCHED_FROM_PASS", 1 if match else None)
    start = disturbed(truth, 2.0, 2.0, seed=4)
    out = refine(images, start, [np.full(len(t), 4.0) for t in truth])
    keep = [img.masks.reshape(len(t), -1).sum(1) >= 60 for img, t in zip(images, truth)]
    return float(np.concatenate([ed(p[k], t[k]) for p, t, k in zip(out.poses, truth, keep)]).mean())


def test_matching_brings_shaded_stacks_closer_to_their_true_poses(shaded, monkeypatch) -> None:  # noqa: ANN001
    """Slices of stacks whose gains differ, step between odd and even slices and fall off across
    the plane are refined nearer their true poses with the fields matched than without."""
    images, truth = shaded
    without, matched = (_refined_error(images, truth, m, monkeypatch) for m in (False, True))
    print(f"shaded stacks refined: E.D. {without:.2f} mm unmatched, {matched:.2f} mm matched")
    assert matched < 0.9 * without, (without, matched)


def test_matching_leaves_clean_stacks_as_they_were_refined(acquisition, monkeypatch) -> None:  # noqa: ANN001
    """On stacks without such fields, matching changes the refined poses' error by little."""
    images, truth = acquisition
    without, matched = (_refined_error(images, truth, m, monkeypatch) for m in (False, True))
    print(f"clean stacks refined: E.D. {without:.2f} mm unmatched, {matched:.2f} mm matched")
    assert matched < without + 0.15, (without, matched)


def test_a_fall_off_along_a_stacks_columns_is_found_in_its_column_slope_at_the_true_poses(acquisition) -> None:  # noqa: ANN001
    """The points' places in a stack's images (:meth:`ImageTerm.pixels`), the images' centre and pixel
    size, and the field divided out (:meth:`Fields.stack_field`) are one grid: a fall-off drawn along
    the second stack's columns at its true poses comes back as that stack's column slope, in log units
    per 100 mm, with no row slope, and its images divided by the field agree with the others again."""
    images, truth = acquisition
    second = images[1]
    n, h, w = second.images.shape
    per_mm = 0.5 / ((w - 1) * second.pixel_mm[1])                             # log intensity per mm along columns
    ramp = np.exp(per_mm * (np.arange(w) - (w - 1) / 2.0) * second.pixel_mm[1])[None, None, :]
    stacks = [images[0], replace(second, images=(second.images * ramp).astype(np.float32)), images[2]]
    sizes = [len(t) for t in truth]
    stack_of, local = np.repeat(np.arange(3), sizes), np.concatenate([np.arange(k) for k in sizes])
    atlas_from_slice = np.concatenate(truth) @ se3.inverse(np.concatenate([s.slice_from_network for s in stacks]))
    sampled = [SampledStack(s, 0.9) for s in stacks]
    term = ImageTerm(sampled, stack_of, local, candidate_pairs(atlas_from_slice, stack_of, np.ones(len(stack_of), bool)),
                     np.arange(-80.0, 80.0, 2.0), atlas_from_slice)
    term.select_in_masks(atlas_from_slice, MIN_LINE_WEIGHT)
    both = term.sw > 0.5
    disagreement = lambda v: float(np.median(np.abs(np.log(np.maximum(v[0][both], 1e-3) / np.maximum(v[1][both], 1e-3)))))  # noqa: E731
    unmatched = disagreement(term.values(atlas_from_slice))
    out, fields = matched(sampled, term, atlas_from_slice, stack_of)
    relative = fields.coefficients[1] - (fields.coefficients[0] + fields.coefficients[2]) / 2.0
    assert relative[3] == pytest.approx(per_mm * SLOPE_SCALE_MM, rel=0.25), fields.coefficients.round(3)
    assert abs(relative[2]) < 0.25 * per_mm * SLOPE_SCALE_MM
    term.use_images(out)
    assert disagreement(term.values(atlas_from_slice)) < 0.8 * unmatched
