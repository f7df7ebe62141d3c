"""JSON text from clients (stream messages, a job's uploaded poses, an MRD session's config), decoded
so that nothing in it can raise anything but :class:`ValueError`.

Python's decoder takes integers of any length and nests as deep as the interpreter's stack allows.
An integer too large for a float (``1`` and 400 zeros) then raises ``OverflowError`` where numpy or
``math`` converts it, and a few thousand ``[`` raise ``RecursionError``: both would end a request as
a server error. Here an integer of more than :data:`MAX_INT_DIGITS` digits becomes a float (infinite
when out of range, which every numeric check refuses as not finite) and too deep a nesting is a
``ValueError``, as malformed JSON is.

Example:
    >>> client_json('{"a": [1, 2.5]}')
    {'a': [1, 2.5]}
    >>> client_json("1" + "0" * 400)
    inf
    >>> client_json("[" * 100000 + "]" * 100000)
    Traceback (most recent call last):
    ...
    ValueError: nested too deeply
"""

from __future__ import annotations

import json
from typing import Any

MAX_INT_DIGITS = 300
"""Longer integers are decoded as floats: every integer up to this length converts to a finite float."""


def _integer(text: str) -> int | float:
    return int(text) if len(text.lstrip("-")) <= MAX_INT_DIGITS else float(text)


def client_json(text: str | bytes) -> Any:
    """The value ``text`` holds; :class:`ValueError` (``json.JSONDecodeError`` among them) when it is
    no JSON or nests too deeply."""
    try:
        return json.loads(text, parse_int=_integer)
    except RecursionError:
        raise ValueError("nested too deeply") from None
