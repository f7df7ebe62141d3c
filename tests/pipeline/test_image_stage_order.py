"""Which stacks the image stage refines together, and against which (:func:`refine_where_stacks_cross`)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from service.pipeline import predict


def _outs(*kinds: str) -> list[SimpleNamespace]:
    """Stage outputs: ``own`` (branch decided by the stack), ``request`` (by the request, the stack
    fitting it on neither branch), ``agrees`` (by the request, the stack sitting with its stacks), ``none``."""
    return [SimpleNamespace(fit=SimpleNamespace(decidable=k != "none", branch_decided=k == "own",
                                                branch_from_request=k in ("request", "agrees"),
                                                branch_known=k in ("own", "agrees"))) for k in kinds]


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> list[tuple[list[int], list[int]]]:
    seen: list[tuple[list[int], list[int]]] = []
    monkeypatch.setattr(predict, "_refine_stacks", lambda prepared, outs, proper, moving, partners, smoothed=None:
                        seen.append((list(moving), list(partners))))
    return seen


def test_stacks_decided_by_the_request_are_refined_after_the_others_against_them(calls) -> None:  # noqa: ANN001
    predict.refine_where_stacks_cross([None] * 5, _outs("own", "request", "own", "none", "own"), [None] * 5)
    assert calls == [([0, 2, 4], []), ([1], [0, 2, 4])]


def test_with_fewer_than_two_self_decided_stacks_all_are_refined_together(calls) -> None:  # noqa: ANN001
    predict.refine_where_stacks_cross([None] * 3, _outs("own", "request", "request"), [None] * 3)
    predict.refine_where_stacks_cross([None] * 3, _outs("own", "own", "none"), [None] * 3)
    predict.refine_where_stacks_cross([None] * 2, _outs("own", "none"), [None] * 2)
    assert calls == [([0, 1, 2], []), ([0, 1], [])]


def test_a_stack_that_agrees_with_the_request_is_refined_with_the_self_decided_ones(calls) -> None:  # noqa: ANN001
    predict.refine_where_stacks_cross([None] * 4, _outs("own", "agrees", "request", "own"), [None] * 4)
    predict.refine_where_stacks_cross([None] * 2, _outs("own", "agrees"), [None] * 2)
    assert calls == [([0, 1, 3], []), ([2], [0, 1, 3]), ([0, 1], [])]
