"""The schemathesis hook makes a generated positive request one the contract calls valid, and leaves
negative ones as generated."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

pytest.importorskip("schemathesis")

from tools.fuzz.hooks import map_case  # noqa: E402


def case(body: dict, positive: bool = True) -> SimpleNamespace:
    mode = SimpleNamespace(is_positive=positive)
    return SimpleNamespace(body=body, meta=SimpleNamespace(generation=SimpleNamespace(mode=mode)))


def test_per_stack_lists_are_cut_to_one_value_and_masks_to_one_per_stack() -> None:
    body = {"stacks": [b"a", b"b"], "masks": [b"m1", b"m2", b"m3"], "slice_order": ["ascending", "interleaved", "x"],
            "slice_thickness_mm": [3.0, 2.0, 4.0]}
    out = map_case(None, case(body)).body
    assert out["masks"] == [b"m1", b"m2"]
    assert out["slice_order"] == ["ascending"]
    assert out["slice_thickness_mm"] == [3.0]


def test_masks_fewer_than_the_stacks_are_dropped() -> None:
    out = map_case(None, case({"stacks": [b"a", b"b"], "masks": [b"m1"]})).body
    assert "masks" not in out


def test_a_negative_case_is_left_as_generated() -> None:
    body = {"stacks": [b"a"], "masks": [b"m1", b"m2"], "slice_thickness_mm": [3.0, 2.0]}
    assert map_case(None, case(dict(body), positive=False)).body == body
