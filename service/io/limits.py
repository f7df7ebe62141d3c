"""How much the files of one request may decode to: per file, and all files of the request together.

Every decoder charges what it produces *while* it produces it (gzip and ZIP inflation, DICOM deflate)
or *before* it allocates it (voxel arrays, from the sizes the header declares), so a bomb is stopped
at the limit, not after it has filled the memory. Voxel arrays are counted as float32 (4 bytes per
value: what the service holds in memory), whatever the stored type.

Example:
    >>> budget = DecodeBudget(per_file=100, per_request=150)
    >>> a, b = budget.file("a.nii.gz"), budget.file("b.nii.gz")
    >>> a.inflate(80); b.inflate(60)
    >>> try:
    ...     b.voxels(20)
    ... except PayloadTooLarge as exc:
    ...     print(exc.detail)
    b.nii.gz: the files of this request decode to more than 0.000143 MB in total
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import threading
from collections.abc import Sequence
from pathlib import Path

from service.core.errors import InsufficientStorage, PayloadTooLarge, UnusableImage

log = logging.getLogger(__name__)
MIN_FREE_BYTES = 64 << 20
"""The free disk a folder the server writes (its data folder, its scratch) must have for ``/readyz``
to call it ready: less takes no upload."""
NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


def folders_take_writes(root: Path, *others: Path) -> bool:
    """Whether the folder ``root`` and ``others`` (folders or files on its disk) can be written (a folder
    entered too) and the disk has :data:`MIN_FREE_BYTES` left: a read-only folder, or a full disk,
    answers reads and fails every upload or submission (``/readyz``'s question for the scratch and the
    job store's folders).

    Example:
        >>> import tempfile
        >>> folders_take_writes(Path(tempfile.mkdtemp())), folders_take_writes(Path("/nonexistent/svrnet"))
        (True, False)
    """
    try:
        room = shutil.disk_usage(root).free >= MIN_FREE_BYTES
    except OSError:
        return False
    return room and all(os.access(p, os.W_OK | (os.X_OK if p.is_dir() else 0)) for p in (root, *others))


def raise_if_out_of_space(exc: BaseException) -> None:
    """Raise :class:`~service.core.errors.InsufficientStorage` (507, logged for the operator) where
    ``exc`` is the disk filling up (``ENOSPC``, ``EDQUOT``): a decoder that catches ``OSError`` to
    name a corrupt file calls this first, so that a full disk is not blamed on the client's file.

    Example:
        >>> raise_if_out_of_space(OSError(errno.EIO, "bad sector"))          # not the disk filling up
        >>> try:
        ...     raise_if_out_of_space(OSError(errno.ENOSPC, "No space left on device"))
        ... except InsufficientStorage as exc:
        ...     print(exc.status)
        507
    """
    if isinstance(exc, OSError) and exc.errno in NO_SPACE:
        log.warning("the disk is full: a request's files could not be written (%s)", errno.errorcode.get(exc.errno))
        raise InsufficientStorage() from exc


def mb(n: int) -> str:
    """``n`` bytes in MB, for messages."""
    return f"{n / 2**20:.3g} MB"


class DecodeBudget:
    """The decoded bytes one request may produce (thread-safe: files are read two at a time)."""

    def __init__(self, per_file: int, per_request: int | None = None, max_slices: int | None = None) -> None:
        self.per_file = int(per_file)
        self.per_request = int(per_request if per_request is not None else per_file)
        self.max_slices = max_slices
        """The most slices a stack may have (a DICOM file's frames, a ZIP's images), checked before
        they are decoded; None: no such limit."""
        self.used = 0
        self._lock = threading.Lock()

    def file(self, filename: str) -> FileBudget:
        """The budget of one file of the request, named ``filename`` in the errors it raises."""
        return FileBudget(self, filename)

    def _charge(self, filename: str, n: int) -> None:
        with self._lock:
            self.used += n
            over = self.used > self.per_request
        if over:
            raise PayloadTooLarge(f"{filename}: the files of this request decode to more than "
                                  f"{mb(self.per_request)} in total")


class FileBudget:
    """One file's share: its inflated streams and its voxel array are each limited to ``per_file``."""

    def __init__(self, request: DecodeBudget, filename: str, parent: FileBudget | None = None) -> None:
        self.request, self.filename, self.parent = request, filename, parent
        self.inflated = 0
        self.voxel_bytes = 0

    def member(self, label: str) -> FileBudget:
        """The same budget, spent by a part of the file (a ZIP member) and naming ``label`` in errors."""
        return FileBudget(self.request, label, self.parent or self)

    @property
    def limit(self) -> int:
        return self.request.per_file

    def slices(self, n: int, what: str) -> None:
        """Refuse, before they are decoded, ``n`` slices (``what``: frames, images) where a stack may
        hold fewer (:attr:`DecodeBudget.max_slices`)."""
        most = self.request.max_slices
        if most is not None and n > most:
            raise UnusableImage(f"{self.filename}: {n} {what}; at most {most} in one stack of 2D slices "
                                "(SVRNET_MAX_SLICES_PER_STACK)")

    def grid(self, sizes: Sequence[int]) -> None:
        """Refuse, from its header, a grid of ``sizes`` voxels that holds more slices than a stack may
        (:attr:`DecodeBudget.max_slices`) along each of its first three axes, whichever of them its
        slices lie along (which one is told by the voxel sizes, once the file is read).

        Example:
            >>> DecodeBudget(1 << 30, max_slices=128).file("a.nii").grid([512, 480, 129])
            Traceback (most recent call last):
            ...
            service.core.errors.UnusableImage: a.nii: a grid of 512 x 480 x 129 voxels holds over 128 slices along each axis; at most 128 in one stack of 2D slices (SVRNET_MAX_SLICES_PER_STACK)
        """
        most = self.request.max_slices
        spatial = [int(n) for n in list(sizes)[:3]]
        if most is not None and len(spatial) == 3 and min(spatial) > most:
            raise UnusableImage(f"{self.filename}: a grid of {' x '.join(map(str, spatial))} voxels holds over {most} "
                                f"slices along each axis; at most {most} in one stack of 2D slices "
                                "(SVRNET_MAX_SLICES_PER_STACK)")

    def too_large(self, what: str = "its data decode") -> PayloadTooLarge:
        return PayloadTooLarge(f"{self.filename}: {what} to more than {mb(self.limit)}")

    def inflate(self, n: int) -> None:
        """Charge ``n`` more bytes produced by a decompressor (gzip, ZIP member, DICOM deflate)."""
        owner = self.parent or self
        owner.inflated += n
        if owner.inflated > self.limit:
            raise self.too_large()
        self.request._charge(self.filename, n)

    def voxels(self, n_values: int) -> None:
        """Charge an array of ``n_values`` voxel values (as float32) before it is allocated; a file's
        parts (a ZIP's images, which make one series) together."""
        n = int(n_values) * 4
        owner = self.parent or self
        owner.voxel_bytes += n
        if owner.voxel_bytes > self.limit:            # a header's word, checked before anything is allocated
            raise owner.declared_too_large(owner.voxel_bytes // 4, "its header declares" if owner is self else
                                           "its images declare")
        self.request._charge(self.filename, n)

    def declared_too_large(self, n_values: int, who: str = "its header declares") -> PayloadTooLarge:
        """The refusal of ``n_values`` voxel values a header declares (as float32) beyond the file's
        limit: what the header says, before anything is decoded or allocated."""
        return PayloadTooLarge(f"{self.filename}: {who} {int(n_values):,} voxels ({mb(int(n_values) * 4)} as float32), "
                               f"more than the {mb(self.limit)} one file may decode to")


__all__ = ["DecodeBudget", "FileBudget", "mb"]
