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
import secrets
from pathlib import Path


def write_whole(path: Path, data: bytes) -> None:
    """``data`` into ``path``, whole or not at all (a partial file of its own beside it, renamed over
    it: threads or processes that write the same file each leave one writer's bytes whole). The file
    gets the mode a plain write gives (0666 less the umask)."""
    partial = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(6)}")
    fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


__all__ = ["write_whole"]
