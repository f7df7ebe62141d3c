"""Schemathesis hooks (``SCHEMATHESIS_HOOKS=tools.fuzz.hooks``): the one rule of API v1 that JSON Schema
cannot state -- ``masks`` are none or one per stack, and ``slice_order`` and ``slice_thickness_mm``
none, one, or one per stack -- applied to generated *positive* cases, so a schema-valid request is one the contract calls valid.
Negative cases are left as generated."""

from __future__ import annotations

from typing import Any

import schemathesis


@schemathesis.hook
def map_case(context: Any, case: Any) -> Any:  # noqa: ANN401 - schemathesis' own types
    """Trim ``masks`` to one per stack, or drop them, and the per-stack lists to one value, in a
    positive multipart body."""
    body = case.body
    mode = getattr(getattr(getattr(case, "meta", None), "generation", None), "mode", None)
    positive = mode is None or getattr(mode, "is_positive", True)
    if positive and isinstance(body, dict) and isinstance(body.get("masks"), list) \
            and isinstance(body.get("stacks"), list):
        masks = body["masks"][: len(body["stacks"])]
        keep = len(masks) == len(body["stacks"])
        case.body = {**body, "masks": masks} if keep else {k: v for k, v in body.items() if k != "masks"}
    for field in ("slice_order", "slice_thickness_mm"):
        body = case.body
        if positive and isinstance(body, dict) and isinstance(body.get(field), list) and len(body[field]) > 1:
            case.body = {**body, field: body[field][:1]}                  # one value serves every stack
    return case
