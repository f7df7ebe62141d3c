r"""The ``multipart/form-data`` body the client uploads: streamed from disk, with a known length.

Kept apart from the HTTP client so that both the body's framing and its encoding of form values are
testable without a server.

Example:
    >>> body = MultipartBody([("mc_samples", form_value(50))], [("stacks", "s.nii.gz", b"abc", "application/gzip")])
    >>> data = b"".join(body.chunks())
    >>> len(data) == body.total and b'name="mc_samples"\r\n\r\n50\r\n' in data
    True
    >>> order_fields(["interleaved", "ascending"])
    [('slice_order', 'interleaved'), ('slice_order', 'ascending')]
"""

from __future__ import annotations

import secrets
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

__all__ = ["CHUNK", "MultipartBody", "ProgressCallback", "form_value", "order_fields", "quote_param"]

CHUNK = 256 * 1024
"""Bytes read from disk (or from the network on a download) at a time."""

ProgressCallback = Callable[[int, int], None]
"""``progress(bytes_sent, total)``, called after every chunk of an upload (or download)."""


def quote_param(value: str) -> str:
    """Escape a ``Content-Disposition`` parameter the way browsers do (HTML5 form encoding)."""
    return value.replace("\\", "\\\\").replace('"', "%22").replace("\r", "%0D").replace("\n", "%0A")


def order_fields(slice_order: str | Sequence[str] | None) -> list[tuple[str, str]]:
    """The repeated ``slice_order`` form field: one value for every stack, or one per stack."""
    orders = [slice_order] if isinstance(slice_order, str) else list(slice_order or [])
    return [("slice_order", str(o)) for o in orders]


class MultipartBody:
    """A ``multipart/form-data`` body streamed from disk in chunks, with a known length.

    Each :meth:`chunks` call yields the whole body again (so a retry can resend it) and reports
    ``progress(bytes_sent, total)`` after every chunk.
    """

    def __init__(self, fields: Sequence[tuple[str, str]],
                 files: Sequence[tuple[str, str, Path | bytes, str]]) -> None:
        self.boundary = secrets.token_hex(16)
        self.parts: list[tuple[bytes, Path | bytes | None]] = []
        for name, value in fields:
            head = (f"--{self.boundary}\r\nContent-Disposition: form-data; name=\"{quote_param(name)}\""
                    f"\r\n\r\n{value}\r\n")
            self.parts.append((head.encode(), None))
        for name, filename, source, content_type in files:
            head = (f"--{self.boundary}\r\nContent-Disposition: form-data; name=\"{quote_param(name)}\"; "
                    f"filename=\"{quote_param(filename)}\"\r\nContent-Type: {content_type}\r\n\r\n")
            self.parts.append((head.encode(), source))
        self.closing = f"--{self.boundary}--\r\n".encode()
        self.total = len(self.closing)
        for head, source in self.parts:
            self.total += len(head)
            if source is not None:
                size = len(source) if isinstance(source, bytes) else Path(source).stat().st_size
                self.total += size + 2

    @property
    def content_type(self) -> str:
        return f"multipart/form-data; boundary={self.boundary}"

    def chunks(self, progress: ProgressCallback | None = None) -> Iterator[bytes]:
        sent = 0

        def emit(data: bytes) -> bytes:
            nonlocal sent
            sent += len(data)
            if progress is not None:
                progress(sent, self.total)
            return data

        if progress is not None:
            progress(0, self.total)
        for head, source in self.parts:
            yield emit(head)
            if source is None:
                continue
            if isinstance(source, bytes):
                for i in range(0, len(source), CHUNK):
                    yield emit(source[i:i + CHUNK])
            else:
                with open(source, "rb") as fh:
                    while data := fh.read(CHUNK):
                        yield emit(data)
            yield emit(b"\r\n")
        yield emit(self.closing)


def form_value(value: object) -> str:
    """A form field's text: booleans as ``true``/``false`` (what the server parses), the rest ``str``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)
