"""The reading side of an MRD connection: reads bounded before the server makes room for them, the
stream's end when it cannot be followed, and the MRD image's names of the fields a refusal names.
"""

from __future__ import annotations

import copy
from typing import BinaryIO

from service.core.errors import PayloadTooLarge, ServiceError

MAX_TEXT_BYTES = 1 << 20
"""The smallest limit on one read from a client (a config, XML header, TEXT or meta string): the
reader allows what the largest image of the pixel limit needs, and never less than this."""
BYTES_PER_VALUE = 16
"""The widest MRD pixel (complex double): what a pixel of an announced image can cost to read."""
MRD_FIELDS = {"slice.scanner_from_voxel": "image header (position, read_dir, phase_dir, slice_dir, field_of_view)",
              "slice.shape": "image matrix_size", "slice.index": "image slice", "slice.stack": "image image_series_index",
              "end_stack.stack": "series", "slice:": "image:"}
"""The streaming core names a slice's fields as Stream v1 does; a scanner knows them by the MRD image's."""


def in_mrd_terms(error: ServiceError) -> ServiceError:
    """``error`` with its detail naming the MRD image's fields instead of Stream v1's.

    Example:
        >>> from service.core.errors import InvalidParameter
        >>> in_mrd_terms(InvalidParameter("slice.index: -1 is negative")).detail
        'image slice: -1 is negative'
    """
    for stream_name, mrd_name in MRD_FIELDS.items():
        if error.detail.startswith(stream_name):
            renamed = copy.copy(error)
            renamed.detail = mrd_name + error.detail[len(stream_name):]
            renamed.args = (renamed.detail,)
            return renamed
    return error


class BoundedReader:
    """A binary stream whose single reads are refused above ``max_read_bytes`` (what a message's length
    fields can make the server read into memory), remembering the last chunk it read.

    Example:
        >>> import io
        >>> r = BoundedReader(io.BytesIO(b"abcdef"), 4)
        >>> r.read(3), r.last
        (b'abc', b'abc')
        >>> r.read(5)
        Traceback (most recent call last):
        ...
        service.core.errors.PayloadTooLarge: message: a field of 5 bytes is over this server's limit of 4
    """

    def __init__(self, raw: BinaryIO, max_read_bytes: int) -> None:
        self.raw, self.max_read_bytes = raw, max_read_bytes
        self.last = b""

    def next_message(self) -> None:
        """A new message is awaited (a reader with a deadline per message starts it now)."""
        if hasattr(self.raw, "next_message"):
            self.raw.next_message()

    def read(self, n: int = -1) -> bytes:
        if n is None or n < 0 or n > self.max_read_bytes:
            raise PayloadTooLarge(f"message: a field of {n} bytes is over this server's limit of {self.max_read_bytes}")
        self.last = self.raw.read(n)
        return self.last


class ProtocolBroken(Exception):
    """The stream cannot be followed past this point: the connection ends after the error is sent."""

    def __init__(self, error: ServiceError) -> None:
        super().__init__(error.detail)
        self.error = error
