"""Stream v1's client messages, read and checked before anything is decoded (``docs/stream.md``).

A text frame is a JSON object with a string ``type`` (:func:`parse`); a ``slice`` message's fields
say what its binary frames hold (:func:`slice_header`): a refused field names itself and no byte of
pixels is read. The websocket's frame cap follows the largest slice allowed (:func:`largest_frame_bytes`).

Example:
    >>> head = slice_header({"type": "slice", "stack": "ax", "index": 3, "shape": [4, 5], "dtype": "uint16",
    ...                      "scanner_from_voxel": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 3, 0], [0, 0, 0, 1]]}, 1024)
    >>> head.stack, head.index, head.shape, head.with_mask
    ('ax', 3, (4, 5), False)
    >>> slice_header({"type": "slice", "stack": "ax", "index": 3, "shape": [4]}, 1024)
    Traceback (most recent call last):
    ...
    service.core.errors.InvalidParameter: slice.shape: [n0, n1], two positive integers (a slice is 2D)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.core.client_json import client_json
from service.core.errors import InvalidParameter, MalformedRequest
from service.core.names import has_unsafe_characters

STREAM_PATH = "/v1/stream"
"""The stream's route (the server's log names it on each handshake, never the path a client sent; an
HTTP request to it is told to upgrade)."""
DTYPES = {"uint8": "<u1", "int16": "<i2", "uint16": "<u2", "float32": "<f4"}
MAX_TEXT_BYTES = 64 * 1024
"""Longest JSON message accepted (a slice's header is a few hundred bytes)."""


def largest_frame_bytes(max_pixels: int) -> int:
    """The server's cap on one websocket frame (a frame past it closes the connection, 1009): the
    largest slice of up to ``max_pixels`` pixels in the widest dtype, or the longest text message.
    A frame the service would refuse anyway is not read into memory first, and a deployment that
    allows larger slices does not have them cut off.

    Example:
        >>> largest_frame_bytes(1024 * 1024), largest_frame_bytes(100)
        (4194304, 65536)
    """
    widest = max(np.dtype(d).itemsize for d in DTYPES.values())
    return max(MAX_TEXT_BYTES, int(max_pixels) * widest)


@dataclass(frozen=True)
class SliceHeader:
    """A ``slice`` message's fields, checked: what its binary frames hold."""

    stack: str
    index: int
    acquisition_index: int | None
    shape: tuple[int, int]
    dtype: str                                    # a key of :data:`DTYPES`
    scanner_from_voxel: NDArray[np.float64]
    with_mask: bool


FIELDS = {"slice": ("type", "stack", "index", "acquisition_index", "shape", "dtype", "scanner_from_voxel", "mask"),
          "end_stack": ("type", "stack"), "end": ("type",), "ping": ("type",)}
"""The fields of each client message but ``start`` (whose options :mod:`service.streaming.options`
checks) and ``auth``: stream-v1.md's, and ``ping`` (answered ``pong``: a sign of life)."""


def known_fields(msg: dict, kind: str) -> dict:
    """``msg`` where it holds no field beyond :data:`FIELDS` ``[kind]``; else :class:`InvalidParameter`
    naming them, as ``start`` refuses an unknown option and ``/v1/predict`` an unknown form field:
    a misspelt ``mask`` must not send a slice without its mask.

    Example:
        >>> known_fields({"type": "end_stack", "stack": "ax"}, "end_stack")["stack"]
        'ax'
        >>> try:
        ...     known_fields({"type": "slice", "maks": True}, "slice")
        ... except InvalidParameter as e:
        ...     print(e)
        slice: unknown fields ['maks'] (type, stack, index, acquisition_index, shape, dtype, scanner_from_voxel, mask)
    """
    unknown = sorted(k for k in msg if k not in FIELDS[kind])
    if unknown:
        raise InvalidParameter(f"{kind}: unknown fields {unknown[:8]} ({', '.join(FIELDS[kind])})")
    return msg


def slice_header(msg: dict, max_pixels: int) -> SliceHeader:
    """The fields of the ``slice`` message ``msg``, each checked (:class:`InvalidParameter` naming it);
    a slice of more than ``max_pixels`` pixels is refused before its frames are read."""
    known_fields(msg, "slice")
    stack = text_field(msg, "stack", "slice")
    index = integer_field(msg, "index", "slice")
    acquisition = integer_field(msg, "acquisition_index", "slice") if msg.get("acquisition_index") is not None else None
    shape = msg.get("shape")
    if not (isinstance(shape, list) and len(shape) == 2 and all(type(n) is int and n > 0 for n in shape)):
        raise InvalidParameter("slice.shape: [n0, n1], two positive integers (a slice is 2D)")
    if shape[0] * shape[1] > max_pixels:
        raise InvalidParameter(f"slice.shape: {shape[0]} x {shape[1]} pixels is over this server's limit of "
                               f"{max_pixels} pixels per slice")
    dtype = msg.get("dtype")
    if dtype not in DTYPES:
        raise InvalidParameter(f"slice.dtype: one of {', '.join(DTYPES)}")
    affine = msg.get("scanner_from_voxel")
    rows = affine if isinstance(affine, list) and len(affine) == 4 else []
    numbers = all(isinstance(r, list) and len(r) == 4 and all(type(v) in (int, float) for v in r) for r in rows)
    if not rows or not numbers:            # numpy would read "3" and true as numbers
        raise InvalidParameter("slice.scanner_from_voxel: a 4 x 4 array of numbers")
    with_mask = msg.get("mask", False)
    if not isinstance(with_mask, bool):
        raise InvalidParameter("slice.mask: true or false")
    return SliceHeader(stack, index, acquisition, (shape[0], shape[1]), dtype, np.array(affine, dtype=np.float64),
                       with_mask)


def parse(text: str) -> dict:
    """A client message: a JSON object with a string ``type`` (:class:`MalformedRequest` otherwise)."""
    if len(text) > MAX_TEXT_BYTES:
        raise MalformedRequest(f"message: {len(text)} characters is over the limit of {MAX_TEXT_BYTES}")
    try:
        msg = client_json(text)
    except ValueError:
        raise MalformedRequest("message: not JSON (or nested too deeply)") from None
    if not isinstance(msg, dict) or not isinstance(msg.get("type"), str):
        raise MalformedRequest("message: a JSON object with a string field type")
    return msg


def is_message(text: str) -> bool:
    """Whether ``text`` is a client message (:func:`parse` takes it), not, say, a slice's pixels sent
    as text where their binary frame was due.

    Example:
        >>> is_message('{"type": "end"}'), is_message("[0, 0, 0]"), is_message("x" * 70000)
        (True, False, False)
    """
    try:
        parse(text)
    except MalformedRequest:
        return False
    return True


def text_field(msg: dict, name: str, kind: str, default: str | None = None) -> str:
    value = msg.get(name, default)
    if not isinstance(value, str) or not 1 <= len(value) <= 128:
        raise InvalidParameter(f"{kind}.{name}: a string of 1 to 128 characters")
    if has_unsafe_characters(value):      # echoed in every answer about it: nothing that could disguise one
        raise InvalidParameter(f"{kind}.{name}: control, format or line-separator characters are not allowed")
    return value


def integer_field(msg: dict, name: str, kind: str) -> int:
    value = msg.get(name)
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < 100_000:
        raise InvalidParameter(f"{kind}.{name}: an integer from 0 to 99999")
    return value
