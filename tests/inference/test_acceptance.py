"""Accept flags: each reason where it applies, and their order of precedence."""

from __future__ import annotations

import numpy as np

from service.inference.acceptance import ATLAS_CENTRE_MM, ATLAS_RADIUS_MM, reasons


def _judged(centres_mm: np.ndarray, **overrides: np.ndarray) -> list[str | None]:
    n = len(centres_mm)
    fields = {"mask_fraction": np.full(n, 0.5), "degenerate": np.zeros(n, bool), "variance": np.ones(n),
              "inconsistent": np.zeros(n, bool), "expected_error_mm": np.full(n, 2.0), **overrides}
    return reasons(fields["mask_fraction"], fields["degenerate"], centres_mm, fields["variance"], 5.0,
                   fields["inconsistent"], fields["expected_error_mm"], 4.0)


def test_a_slice_centred_beyond_the_atlas_radius_is_outside_the_atlas_in_any_direction() -> None:
    """Slice centres 1 mm inside and 1 mm outside the atlas's radius, along each axis and a diagonal,
    about the atlas brain's centre (not the origin): the outer ones alone are ``outside_atlas``."""
    directions = np.vstack([np.eye(3), -np.eye(3), np.ones((1, 3)) / np.sqrt(3.0)])
    inside = ATLAS_CENTRE_MM + (ATLAS_RADIUS_MM - 1.0) * directions
    outside = ATLAS_CENTRE_MM + (ATLAS_RADIUS_MM + 1.0) * directions
    assert _judged(inside) == [None] * len(directions)
    assert _judged(outside) == ["outside_atlas"] * len(directions)
    below = np.array([[0.0, 0.0, -65.0]])                 # 65 mm from the origin, 73 from the brain's centre
    assert np.linalg.norm(below - ATLAS_CENTRE_MM) > ATLAS_RADIUS_MM > np.linalg.norm(below)
    assert _judged(below) == ["outside_atlas"]


def test_reasons_take_their_contract_s_precedence() -> None:
    """A slice outside the atlas that is also empty is ``empty``; one that is also degenerate is
    ``degenerate_anchor_points``; one that is also inconsistent, unsure or of a high expected error
    is ``outside_atlas``."""
    far = np.tile(ATLAS_CENTRE_MM + [ATLAS_RADIUS_MM + 5.0, 0.0, 0.0], (5, 1))
    got = _judged(far, mask_fraction=np.array([0.0, 0.5, 0.5, 0.5, 0.5]),
                  degenerate=np.array([False, True, False, False, False]),
                  inconsistent=np.array([True, True, True, False, False]),
                  variance=np.array([9.0, 9.0, 9.0, 9.0, 1.0]),
                  expected_error_mm=np.array([9.0, 9.0, 9.0, 9.0, 9.0]))
    assert got == ["empty", "degenerate_anchor_points", "outside_atlas", "outside_atlas", "outside_atlas"]
