"""Uploaded files: spooled into a private temporary directory, read, and deleted with it."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from fastapi import UploadFile

from service.core.errors import InvalidParameter
from service.inference.pipeline import StackUpload
from service.io.readers import read_upload


@contextmanager
def upload_directory(base: Path | None) -> Iterator[Path]:
    """A private directory for this request's files, removed afterwards whatever happens."""
    with tempfile.TemporaryDirectory(prefix="svrnet-req-", dir=base) as tmp:
        yield Path(tmp)


def display_name(upload: UploadFile, field: str, index: int) -> str:
    """The client's file name (for messages to the client only), or ``field[index]``."""
    name = Path(upload.filename or "").name
    return name or f"{field}[{index}]"


def save_and_read(stacks: list[UploadFile], masks: list[UploadFile], directory: Path) -> list[StackUpload]:
    """Write each upload to ``directory`` and read it (blocking: run in a worker thread)."""
    if len(masks) > len(stacks):
        raise InvalidParameter(f"masks: {len(masks)} masks for {len(stacks)} stacks; give none or one per stack")
    if masks and len(masks) != len(stacks):
        raise InvalidParameter(f"masks: {len(masks)} masks for {len(stacks)} stacks; give none or one per stack")
    out = []
    for i, up in enumerate(stacks):
        vol = _read(up, directory / f"stack{i}", display_name(up, "stacks", i))
        mask, mask_name = None, None
        if masks:
            mask_name = display_name(masks[i], "masks", i)
            mask = _read(masks[i], directory / f"mask{i}", mask_name)
        out.append(StackUpload(display_name(up, "stacks", i), vol, mask, mask_name))
    return out


def _read(upload: UploadFile, path: Path, name: str):  # noqa: ANN202
    upload.file.seek(0)
    with open(path, "wb") as f:
        shutil.copyfileobj(upload.file, f, 1 << 20)
    return read_upload(path, name)
