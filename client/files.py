"""Files the client writes: each whole or not at all (standard library only: ``import client`` stays light).

Example:
    >>> import tempfile
    >>> target = Path(tempfile.mkdtemp()) / "answer.json"
    >>> write_whole(target, b"{}")
    >>> target.read_bytes(), sorted(p.name for p in target.parent.iterdir())
    (b'{}', ['answer.json'])
"""

from __future__ import annotations

import os
from pathlib import Path


def write_whole(path: Path, data: bytes) -> None:
    """``data`` into ``path``, whole or not at all (a partial file beside it, renamed over it)."""
    partial = path.with_name(f".{path.name}.{os.getpid()}")
    try:
        partial.write_bytes(data)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


__all__ = ["write_whole"]
