"""A brain that runs out of the picture is told from one the picture is cropped tight about, at every
edge, for round and flat outlines and the pixel sizes scanners write."""

from __future__ import annotations

import numpy as np
import pytest

from service.preprocess.field_of_view import MIN_EDGE_WIDTH_MM, cut_by_field_of_view


def ellipse(pixel_mm: float, radii_mm: tuple[float, float], size_mm: float = 200.0) -> np.ndarray:
    """A slice's brain: an ellipse of ``radii_mm`` (rows, columns) at the centre of a picture."""
    n = int(round(size_mm / pixel_mm))
    yy, xx = (np.mgrid[:n, :n] - (n - 1) / 2) * pixel_mm
    return (yy / radii_mm[0]) ** 2 + (xx / radii_mm[1]) ** 2 <= 1.0


def crop(mask: np.ndarray, margin_px: int = 0) -> np.ndarray:
    """``mask`` cropped to its box (plus ``margin_px``), as a stack cut to its mask is uploaded."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    return mask[max(rows[0] - margin_px, 0):rows[-1] + 1 + margin_px, max(cols[0] - margin_px, 0):cols[-1] + 1 + margin_px]


@pytest.mark.parametrize("pixel_mm", [0.5, 0.8, 1.125, 1.6])
@pytest.mark.parametrize("radii_mm", [(40.0, 32.0), (25.0, 20.0), (45.0, 25.0), (20.0, 45.0)])
def test_a_brain_cropped_tight_or_whole_is_not_cut(pixel_mm: float, radii_mm: tuple[float, float]) -> None:
    brain = ellipse(pixel_mm, radii_mm)
    for picture in (brain, crop(brain), crop(brain, 1), crop(brain, 3)):
        assert not cut_by_field_of_view(picture[None], (pixel_mm, pixel_mm)).any()


@pytest.mark.parametrize("pixel_mm", [0.5, 0.8, 1.125, 1.6])
@pytest.mark.parametrize("edge", ["top", "bottom", "left", "right"])
def test_a_brain_the_picture_ends_inside_is_cut_at_any_edge(pixel_mm: float, edge: str) -> None:
    brain = crop(ellipse(pixel_mm, (40.0, 32.0)))
    depth = int(round(6.0 / pixel_mm))                           # the picture ends 6 mm inside the brain
    cut = {"top": brain[depth:], "bottom": brain[:-depth], "left": brain[:, depth:], "right": brain[:, :-depth]}[edge]
    assert cut_by_field_of_view(cut[None], (pixel_mm, pixel_mm)).tolist() == [True]


def test_pixels_of_two_pitches_are_measured_each_along_its_own_axis() -> None:
    """Rows 0.7 mm apart, columns 1.4 mm: the brain's width and depth in millimetres, not pixels."""
    yy, xx = np.mgrid[:200, :100]
    brain = ((yy - 100) * 0.7 / 40) ** 2 + ((xx - 50) * 1.4 / 32) ** 2 <= 1.0
    rows = np.flatnonzero(brain.any(1))
    tight = brain[rows[0]:rows[-1] + 1]
    assert not cut_by_field_of_view(tight[None], (0.7, 1.4)).any()
    assert cut_by_field_of_view(tight[int(8 / 0.7):][None], (0.7, 1.4)).all()


def test_a_pole_or_sliver_at_the_edge_is_not_judged() -> None:
    """A brain meeting the edge over less than the minimum width tells nothing."""
    picture = np.zeros((1, 60, 60), bool)
    picture[0, :20, 20:20 + int(MIN_EDGE_WIDTH_MM) - 1] = True           # a narrow band running off the top
    assert not cut_by_field_of_view(picture, (1.0, 1.0)).any()
    picture[0, :20, 20:20 + int(MIN_EDGE_WIDTH_MM) + 1] = True
    assert cut_by_field_of_view(picture, (1.0, 1.0)).all()


def test_slices_are_judged_each_on_its_own_and_an_empty_one_is_not_cut() -> None:
    brain = crop(ellipse(1.0, (40.0, 32.0)))
    slices = np.stack([brain, np.zeros_like(brain), np.pad(brain[10:], ((0, 10), (0, 0)))])
    assert cut_by_field_of_view(slices, (1.0, 1.0)).tolist() == [False, False, True]


@pytest.mark.parametrize("pixel_mm", [0.8, 1.125, 1.6])
def test_a_crop_tight_about_the_brain_through_its_csf_rim_is_not_a_cut_of_it(pixel_mm: float) -> None:
    """A mask that holds the CSF around the brain (2 mm wide), cropped tight about the brain: the
    picture cuts the CSF alone; 6 mm past the brain's edge it cuts the brain."""
    brain = crop(ellipse(pixel_mm, (40.0, 32.0)))
    rim = int(round(2.0 / pixel_mm))
    with_csf = ellipse(pixel_mm, (42.0, 34.0), size_mm=200.0)
    rows, cols = np.flatnonzero(with_csf.any(1)), np.flatnonzero(with_csf.any(0))
    tight = with_csf[rows[0] + rim:rows[-1] + 1 - rim, cols[0] + rim:cols[-1] + 1 - rim]    # the brain's box
    assert tight.shape == brain.shape or abs(tight.shape[0] - brain.shape[0]) <= 2
    assert not cut_by_field_of_view(tight[None], (pixel_mm, pixel_mm), beyond_mm=2.0).any()
    deeper = int(round(6.0 / pixel_mm))
    assert cut_by_field_of_view(tight[deeper:][None], (pixel_mm, pixel_mm), beyond_mm=2.0).all()


def test_the_depth_of_a_cut_is_that_of_the_round_outline_through_both_widths() -> None:
    from service.preprocess.field_of_view import cut_depth_mm

    r, apart = 25.0, 5.0
    for depth in (0.5, 3.0, 10.0, 30.0):                               # past the centre too
        chord = lambda d: 2 * np.sqrt(d * (2 * r - d))  # noqa: E731
        assert cut_depth_mm(np.array([chord(depth)]), np.array([chord(depth + apart)]), apart)[0] == pytest.approx(depth)


def test_a_brain_no_narrower_inside_than_at_the_edge_is_cut_whatever_its_csf() -> None:
    """A band as wide at the edge as inside (the edge through its middle) fits no round outline."""
    band = np.zeros((1, 40, 40), bool)
    band[0, :20, 14:26] = True                                       # 12 mm wide, running off the first row
    for beyond in (0.0, 2.0):
        assert cut_by_field_of_view(band, (1.0, 1.0), beyond_mm=beyond).all()
