"""What every ONNX model of the service shares: its CPU session options and the file's checksum.

Example:
    >>> session_options(2).intra_op_num_threads
    2
    >>> session_threads(1), session_threads(4, cores=4), session_threads(0, cores=4)
    ((1, False), (4, False), (2, True))
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import onnxruntime as ort

from service.core.threads import available_cores


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file (hex), read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def model_files(folder: Path) -> list[Path]:
    """The ``<name>/model.onnx`` files of a models folder, by name; folders whose name starts with a dot
    are left out (a model being shipped into place, ``svrnet-train ship``'s ``.<name>.shipping``).

    Example:
        >>> import tempfile
        >>> root = Path(tempfile.mkdtemp())
        >>> for name in ("default", ".default.shipping"):
        ...     (root / name).mkdir(); _ = (root / name / "model.onnx").write_bytes(b"")
        >>> [p.parent.name for p in model_files(root)]
        ['default']
    """
    return sorted(p for p in Path(folder).glob("*/model.onnx") if not p.parent.name.startswith("."))


def session_options(threads: int = 0) -> ort.SessionOptions:
    """CPU session options: all graph optimisations (the pose models' dropout masks survive them), no
    spinning; ``threads`` 0 means all cores."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.intra_op_num_threads = threads
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return opts


def session_threads(threads: int = 0, cores: int | None = None) -> tuple[int, bool]:
    """A session's intra-op threads, and whether its calls run two at a time
    (:func:`~service.core.threads.side_by_side`). ``threads`` 0 (all of the machine's ``cores``,
    two or more): half the cores a call, two calls at a time; a small network's convolutions gain
    less from a second intra-op thread than from a second call. Otherwise ``threads``, one call at
    a time."""
    cores = available_cores() if cores is None else cores
    if threads == 0 and cores >= 2:
        return cores // 2, True
    return threads, False
