"""Coverage of the brain by a session's slices, against what is known of simulated ones: the hull's
inside agrees with an independent point location, a stack of every slice covers its whole hull (of
the volume the hull has), and a missing slice is a gap along the stack's normal."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, Delaunay

from service.geometry import se3
from service.streaming.coverage import CoveredSlice, brain_points, coverage, inside_hull


def ball_stack(rotation: np.ndarray, keep: list[int] | None = None, n: int = 20, px: float = 1.2,
               thick: float = 3.0) -> list[CoveredSlice]:
    """Slices of a 35 mm ball, ``thick`` mm apart along the third column of ``rotation``, 64 x 64 px."""
    out = []
    for k in range(n) if keep is None else keep:
        a = np.eye(4)
        a[:3, :3] = rotation @ np.diag([px, px, thick])
        z = (k - n / 2) * thick
        a[:3, 3] = rotation @ np.array([-32 * px, -32 * px, z])
        i, j = np.meshgrid(np.arange(64), np.arange(64), indexing="ij")
        out.append(CoveredSlice(a, ((i - 32) * px) ** 2 + ((j - 32) * px) ** 2 + z ** 2 < 35.0 ** 2))
    return out


def test_inside_the_hull_agrees_with_a_delaunay_point_location() -> None:
    rng = np.random.default_rng(5)
    points = rng.normal(size=(300, 3)) * [30, 20, 25]
    queries = rng.uniform(-80, 80, size=(20000, 3))
    expected = Delaunay(points).find_simplex(queries) >= 0
    np.testing.assert_array_equal(inside_hull(ConvexHull(points), queries), expected)


def test_a_stack_of_every_slice_covers_its_whole_hull() -> None:
    rotation = se3.so3_exp(np.array([0.3, -0.5, 0.2]))            # an oblique stack: the lattice of planes
    slices = ball_stack(rotation)
    c = coverage(slices)
    assert c.brain_fraction > 0.999 and c.gaps == []                  # a grid point at the rim, at most
    hull_ml = ConvexHull(brain_points(slices)).volume / 1000.0
    assert abs(c.brain_volume_ml - hull_ml) < 0.1 * hull_ml, (c.brain_volume_ml, hull_ml)


def test_a_slice_not_accepted_is_a_gap_along_the_stacks_normal() -> None:
    rotation = se3.so3_exp(np.array([0.3, -0.5, 0.2]))
    c = coverage(ball_stack(rotation, keep=[k for k in range(20) if k != 10]), ball_stack(rotation))
    assert 0.85 < c.brain_fraction < 1.0 and len(c.gaps) == 1
    assert abs(abs(np.dot(c.gaps[0].normal, rotation[:, 2])) - 1.0) < 0.1, c.gaps[0].normal
    assert 1.5 <= c.gaps[0].extent_mm <= 6.0, c.gaps[0].extent_mm


def test_the_brain_is_what_every_slice_shows_and_only_accepted_slices_cover_it() -> None:
    """The middle half of a stack accepted: about half the brain its slices show is covered (counted
    on the accepted slices alone, their hull, it was all covered)."""
    rotation = se3.so3_exp(np.array([0.1, 0.2, -0.3]))
    middle = ball_stack(rotation, keep=list(range(5, 15)))
    alone, shown = coverage(middle), coverage(middle, ball_stack(rotation))
    assert alone.brain_fraction > 0.95
    assert 0.45 < shown.brain_fraction < 0.8 and shown.brain_volume_ml > 1.5 * alone.brain_volume_ml


def test_the_hulls_bridge_over_a_concave_brain_is_no_brain_and_no_gap() -> None:
    """Two lobes side by side, every slice accepted: the waist between them, inside their hull, lies
    beyond the slices' brain pixels; counted as brain it was an uncovered gap no stack can fill."""
    slices = []
    for k in range(30):
        a = np.diag([1.2, 1.2, 3.0, 1.0])
        z = (k - 15) * 3.0
        a[:3, 3] = (-48.0, -48.0, z)
        i, j = np.meshgrid(np.arange(80), np.arange(80), indexing="ij")
        x, y = (i - 40) * 1.2, (j - 40) * 1.2
        lobes = ((x - 24) ** 2 + y ** 2 + z ** 2 < 18.0 ** 2) | ((x + 24) ** 2 + y ** 2 + z ** 2 < 18.0 ** 2)
        slices.append(CoveredSlice(a, lobes))
    c = coverage(slices)
    assert c.brain_fraction > 0.98 and c.gaps == [], (c.brain_fraction, c.gaps)
    two_balls_ml = 2 * 4 / 3 * np.pi * 18.0 ** 3 / 1000.0
    assert c.brain_volume_ml < 1.25 * two_balls_ml < ConvexHull(brain_points(slices)).volume / 1000.0


def test_coverage_without_a_volume_says_it_is_not_measured() -> None:
    """No accepted slice, or accepted slices in one plane: the brain's extent is unknown, and the
    report says so rather than read as a brain with no gaps."""
    rotation = np.eye(3)
    assert coverage([]).report()["measured"] is False
    one = ball_stack(rotation, keep=[10])
    assert coverage(one).report() == {"brain_fraction": 0.0, "brain_volume_ml": 0.0, "gaps": [], "measured": False}
    assert coverage(ball_stack(rotation)).report()["measured"] is True


def test_masks_over_the_whole_field_of_view_count_the_atlas_brains_reach_alone() -> None:
    """Four slices of 640 mm fields of view whose masks are all brain (a client's, accepted by its own
    thresholds) in four orientations: coverage counts only what lies within the atlas brain's reach,
    so its grid stays that size (the whole fields of view made a grid of gigabytes and 4.7 litres)."""
    from service.inference.acceptance import ATLAS_CENTRE_MM
    from service.streaming.coverage import BRAIN_REACH_MM

    rng = np.random.default_rng(2)
    slices = []
    for _ in range(4):
        turn = se3.exp(np.concatenate([rng.normal(0, 1, 3), np.zeros(3)]))[:3, :3]
        a = np.eye(4)
        a[:3, :3] = turn @ np.diag([2.5, 2.5, 3.0])
        a[:3, 3] = ATLAS_CENTRE_MM - turn @ np.array([320.0, 320.0, 0.0])
        slices.append(CoveredSlice(a, np.ones((256, 256), bool)))
    pts = brain_points(slices, every=True)
    assert np.linalg.norm(pts - ATLAS_CENTRE_MM, axis=1).max() <= BRAIN_REACH_MM
    c = coverage(slices)
    assert c.measured and 0 < c.brain_volume_ml <= 4 / 3 * np.pi * BRAIN_REACH_MM ** 3 / 1000
