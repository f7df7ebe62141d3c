"""The reading side of an MRD connection: reads bounded before the server makes room for them, the
stream's end when it cannot be followed, and the MRD image's names of the fields a refusal names.
"""

from __future__ import annotations

import copy
import ctypes
import math
import struct
from typing import BinaryIO

import ismrmrd
from ismrmrd.serialization import ISMRMRDMessageID

from service.core.errors import PayloadTooLarge, ServiceError, UnusableImage
from service.mrd.images import pixel_count, shape_problem

MAX_TEXT_BYTES = 1 << 20
"""The smallest limit on one read from a client (a config, XML header, TEXT or meta string): the
reader allows what the largest image of the pixel limit needs, and never less than this."""
MAX_META_BYTES = 1 << 18
"""An image's meta attributes (an XML text) are refused above this many bytes before they are read:
parsed into a tree, a text of empty elements takes over twenty times its size in memory."""
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
        self.ahead = b""                               # bytes :meth:`peek` read, which the next reads return first

    def next_message(self) -> None:
        """A new message is awaited (a reader with a deadline per message starts it now)."""
        if hasattr(self.raw, "next_message"):
            self.raw.next_message()

    def read(self, n: int = -1) -> bytes:
        if n is None or n < 0 or n > self.max_read_bytes:
            raise PayloadTooLarge(f"message: a field of {n} bytes is over this server's limit of {self.max_read_bytes}")
        first, self.ahead = self.ahead[:n], self.ahead[n:]
        self.last = first + self.raw.read(n - len(first)) if len(first) < n else first
        return self.last

    def peek(self, n: int) -> bytes:
        """The next ``n`` bytes (fewer at the stream's end), which the next reads still return.

        Example:
            >>> import io
            >>> r = BoundedReader(io.BytesIO(b"abcdef"), 4)
            >>> r.peek(2), r.read(3), r.read(3)
            (b'ab', b'abc', b'def')
        """
        if len(self.ahead) < n:
            self.ahead += self.raw.read(n - len(self.ahead))
        return self.ahead[:n]


SKIP_CHUNK_BYTES = 1 << 20
"""Raw data are read past in chunks of at most this many bytes."""
NDARRAY_HEAD = struct.Struct("<HHH")                 # data type, version, number of dimensions


def raw_payload_bytes(kind: int, reader: BoundedReader) -> int:
    """The bytes that follow the head of a raw-data message (acquisition, waveform, NDArray), read
    here from ``reader`` past the message id: what ``ismrmrd`` would allocate for before it reads them
    (struct.error: an NDArray of an unknown element type).

    Example:
        >>> import io
        >>> head = ismrmrd.AcquisitionHeader(number_of_samples=16, active_channels=2, trajectory_dimensions=0)
        >>> raw_payload_bytes(ISMRMRDMessageID.ACQUISITION, BoundedReader(io.BytesIO(bytes(head)), 1 << 20))
        256
    """
    if kind == ISMRMRDMessageID.ACQUISITION:
        acq = ismrmrd.AcquisitionHeader.from_buffer_copy(read_exactly(reader, ctypes.sizeof(ismrmrd.AcquisitionHeader)))
        return acq.number_of_samples * (acq.trajectory_dimensions * 4 + acq.active_channels * 8)
    if kind == ISMRMRDMessageID.WAVEFORM:
        wave = ismrmrd.WaveformHeader.from_buffer_copy(read_exactly(reader, ctypes.sizeof(ismrmrd.WaveformHeader)))
        return wave.channels * wave.number_of_samples * 4
    data_type, _, ndim = NDARRAY_HEAD.unpack(read_exactly(reader, NDARRAY_HEAD.size))
    if data_type not in ismrmrd.image.dtype_mapping:
        raise struct.error(f"unknown data type {data_type}")
    dims = struct.unpack(f"<{ndim}Q", read_exactly(reader, 8 * ndim))
    return math.prod(dims) * ismrmrd.image.dtype_mapping[data_type].itemsize


def skip_raw_message(kind: int, reader: BoundedReader) -> None:
    """Read past a raw-data message (the server takes images only) without building it: its payload,
    as its head announces it, is refused above the reader's limit before a byte of it is read.

    Example:
        >>> import io
        >>> head = ismrmrd.WaveformHeader(channels=1, number_of_samples=4)
        >>> stream = io.BytesIO(bytes(head) + bytes(16) + b"next")
        >>> skip_raw_message(ISMRMRDMessageID.WAVEFORM, BoundedReader(stream, 1 << 20)); stream.read()
        b'next'
    """
    left = raw_payload_bytes(kind, reader)
    if left > reader.max_read_bytes:
        name = ISMRMRDMessageID(kind).name.lower()
        raise PayloadTooLarge(f"{name}: its head announces {left} bytes of data, over this server's limit of "
                              f"{reader.max_read_bytes}")
    read_past(reader, left)


def read_past(reader: BoundedReader, n: int) -> None:
    """Read ``n`` bytes of ``reader`` and keep none: in chunks of :data:`SKIP_CHUNK_BYTES`, whatever ``n``
    (EOFError where the stream ends first).

    Example:
        >>> import io
        >>> r = BoundedReader(io.BytesIO(bytes(5) + b"next"), 1 << 20); read_past(r, 5); r.read(4)
        b'next'
    """
    while n > 0:
        n -= len(read_exactly(reader, min(n, SKIP_CHUNK_BYTES)))


def read_exactly(reader: BoundedReader, n: int) -> bytes:
    """``n`` bytes from ``reader``; EOFError where the stream ends first."""
    chunk = reader.read(n)
    if len(chunk) < n:
        raise EOFError("the stream ended inside a message")
    return chunk


class ProtocolBroken(Exception):
    """The stream cannot be followed past this point: the connection ends after the error is sent."""

    def __init__(self, error: ServiceError) -> None:
        super().__init__(error.detail)
        self.error = error


IMAGE_HEADER_BYTES = ctypes.sizeof(ismrmrd.ImageHeader)
META_LENGTH = struct.Struct("<Q")                    # the length of an image's meta attributes, after its header
MAX_SKIPPED_IMAGE_BYTES = 256 * 2**20
"""The most data of an image of a shape the stream cannot use (a volume, uncombined coils) the server
reads past, in chunks, to answer it with an error and go on; beyond it the connection ends (413)."""


def read_past_unusable_image(reader: BoundedReader, max_pixels: int) -> tuple[UnusableImage, int, int] | None:
    """Judge an image by the header ``reader`` has just read (its last chunk; the meta attributes'
    length follows), before its data: :class:`ProtocolBroken` where it announces an unknown data
    type, meta attributes over :data:`MAX_META_BYTES` or more than ``max_pixels`` values; where its
    shape is one the stream cannot use (:func:`~service.mrd.images.shape_problem`) and its data are at
    most :data:`MAX_SKIPPED_IMAGE_BYTES`, the rest of the message is read past, never built, and its
    problem returned with the image's series and slice; None for an image to read.

    Example (a volume of 8 x 8 x 4 values, read past; what follows it is left to read):
        >>> import io
        >>> head = ismrmrd.ImageHeader(); head.matrix_size[:] = (8, 8, 4); head.channels = 1
        >>> head.data_type = ismrmrd.DATATYPE_FLOAT
        >>> r = BoundedReader(io.BytesIO(bytes(head) + META_LENGTH.pack(0) + bytes(4 * 256) + b"next"), 1 << 20)
        >>> _ = r.read(IMAGE_HEADER_BYTES)
        >>> problem, series, index = read_past_unusable_image(r, 4096)
        >>> str(problem), r.read(4)
        ('matrix_size: a 3D image (8 x 8 x 4); svrnet-mrd takes 2D images', b'next')
    """
    head = ismrmrd.ImageHeader.from_buffer_copy(reader.last[:IMAGE_HEADER_BYTES])
    if int(head.data_type) not in ismrmrd.image.dtype_mapping:
        raise ProtocolBroken(UnusableImage(f"image.data_type: unknown code {int(head.data_type)}"))
    ahead = reader.peek(META_LENGTH.size)
    meta_bytes = META_LENGTH.unpack(ahead)[0] if len(ahead) == META_LENGTH.size else 0   # short: the stream ends
    if meta_bytes > MAX_META_BYTES:
        raise ProtocolBroken(PayloadTooLarge(
            f"image: meta attributes of {meta_bytes} bytes are over this server's limit of {MAX_META_BYTES}"))
    data_bytes = pixel_count(head) * ismrmrd.image.dtype_mapping[int(head.data_type)].itemsize
    if (problem := shape_problem(head)) is not None and data_bytes <= MAX_SKIPPED_IMAGE_BYTES:
        read_past(reader, META_LENGTH.size + meta_bytes + data_bytes)
        return problem, int(head.image_series_index), int(head.slice)
    if pixel_count(head) > max_pixels:
        raise ProtocolBroken(PayloadTooLarge(f"image: {pixel_count(head)} values (channels x matrix_size) is over "
                                             f"this server's limit of {max_pixels} pixels per image"))
    return None
