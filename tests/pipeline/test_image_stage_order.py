"""Which stacks the image stage refines together, and against which (:func:`refine_where_stacks_cross`)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from service.pipeline import image_stage
from service.pipeline.unseen_errors import add_unseen_errors


def _outs(*kinds: str) -> list[SimpleNamespace]:
    """Stage outputs: ``own`` (branch decided by the stack), ``request`` (by the request, the stack
    fitting it on neither branch), ``agrees`` (by the request, the stack sitting with its stacks), ``none``,
    ``apart`` (decided by the stack, its brain another fetus's)."""
    return [SimpleNamespace(fit=SimpleNamespace(decidable=k != "none", branch_decided=k in ("own", "apart"),
                                                branch_from_request=k in ("request", "agrees"),
                                                branch_known=k in ("own", "agrees", "apart"), mirrored=False),
                            apart=k == "apart") for k in kinds]


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> list[tuple[list[int], list[int]]]:
    seen: list[tuple[list[int], list[int]]] = []
    monkeypatch.setattr(image_stage, "_refine_stacks", lambda prepared, outs, proper, moving, partners, smoothed=None:
                        seen.append((list(moving), list(partners))))
    return seen


def test_stacks_decided_by_the_request_are_refined_after_the_others_against_them(calls) -> None:  # noqa: ANN001
    image_stage.refine_where_stacks_cross([None] * 5, _outs("own", "request", "own", "none", "own"), [None] * 5)
    assert calls == [([0, 2, 4], []), ([1], [0, 2, 4])]


def test_with_fewer_than_two_self_decided_stacks_all_are_refined_together(calls) -> None:  # noqa: ANN001
    image_stage.refine_where_stacks_cross([None] * 3, _outs("own", "request", "request"), [None] * 3)
    image_stage.refine_where_stacks_cross([None] * 3, _outs("own", "own", "none"), [None] * 3)
    image_stage.refine_where_stacks_cross([None] * 2, _outs("own", "none"), [None] * 2)
    assert calls == [([0, 1, 2], []), ([0, 1], [])]


def test_a_stack_that_agrees_with_the_request_is_refined_with_the_self_decided_ones(calls) -> None:  # noqa: ANN001
    image_stage.refine_where_stacks_cross([None] * 4, _outs("own", "agrees", "request", "own"), [None] * 4)
    image_stage.refine_where_stacks_cross([None] * 2, _outs("own", "agrees"), [None] * 2)
    assert calls == [([0, 1, 3], []), ([2], [0, 1, 3]), ([0, 1], [])]


def test_a_stack_of_another_fetus_is_refined_with_none(calls) -> None:  # noqa: ANN001
    image_stage.refine_where_stacks_cross([None] * 4, _outs("own", "apart", "request", "own"), [None] * 4)
    image_stage.refine_where_stacks_cross([None] * 2, _outs("own", "apart"), [None] * 2)
    assert calls == [([0, 3], []), ([2], [0, 3])]


def _placed(sd: float | None, pooled: bool = True) -> SimpleNamespace:
    """A stage output of three slices with expected errors of 9 mm, placed to ``sd`` mm per coordinate."""
    import numpy as np

    fit = SimpleNamespace(placement_sd_mm=sd if not pooled else 99.0, decidable=True, branch_decided=True,
                          branch_from_request=False, branch_known=True, mirrored=False)
    return SimpleNamespace(poses=np.repeat(np.eye(4)[None], 3, 0), expected_error_mm=np.full(3, 9.0),
                           inconsistent=np.zeros(3, bool), fit=fit,
                           pooled=SimpleNamespace(placement_sd_mm=sd) if pooled else None, image_consistency=None)


@pytest.mark.parametrize("sds, floor", [((4.0, 6.0), 4.0 * 3 ** 0.5), ((4.0, 1.0), 3 ** 0.5)])
def test_the_images_place_no_slice_better_than_the_best_placed_stack(monkeypatch: pytest.MonkeyPatch, sds, floor) -> None:  # noqa: ANN001
    """Two stacks whose images agree where they cross (a sharp refinement: 1 mm) are placed in the
    atlas no better than the better placed of them: with placements of 4 and 6 mm per coordinate
    every slice's returned expected error is at least sqrt(3) x 4 mm (the pooled placement's, not
    the stack's own 99 mm); beside a stack placed to 1 mm (not pooled: its own placement),
    sqrt(3) x 1 mm, the model's own floor no longer added on top of it."""
    import numpy as np

    outs = [_placed(sds[0]), _placed(sds[1], pooled=False)]
    monkeypatch.setattr(image_stage, "stack_images", lambda prepared, active=None, fixed=False: SimpleNamespace(active=active))
    monkeypatch.setattr(image_stage, "refine", lambda images, poses, expected, smoothed=None: SimpleNamespace(
        poses=poses, mismatch=[np.zeros(3)] * 2, moved_mm=[np.zeros(3)] * 2, pairs=4, cost_before=1.0, cost_after=0.5,
        spread_mm=[np.ones(3)] * 2))
    monkeypatch.setattr(image_stage, "relative_mismatch", lambda mismatch: [np.ones(3)] * 2)
    monkeypatch.setattr(image_stage, "expected_after", lambda expected, relative, spread: [np.ones(3)] * 2)
    image_stage._refine_stacks([None, None], outs, [np.ones(3, bool)] * 2, [0, 1], [])
    info = SimpleNamespace(expected_error_floor_mm=0.5, twin_risk_logit=None)
    for out in outs:
        assert out.image_consistency.placement_floor_mm == pytest.approx(floor)
        add_unseen_errors(out, info)                   # the floor is the whole error, not a term
        np.testing.assert_allclose(out.expected_error_mm, max(floor, np.hypot(1.0, 0.5)))
