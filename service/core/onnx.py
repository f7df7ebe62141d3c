"""What every ONNX model of the service shares: its CPU session options, how its calls share the
cores (:class:`SideBySide`), and the file's checksum.

Example:
    >>> session_options(2).intra_op_num_threads
    2
    >>> SideBySide(2).map(lambda k: k * k, [1, 2, 3])
    [1, 4, 9]
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeVar

import onnxruntime as ort

from service.core.machine import usable_cores
from service.core.threads import ProcessThreads

T = TypeVar("T")
R = TypeVar("R")


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


class SideBySide:
    """A model's onnxruntime calls run side by side, each on one core.

    The service's networks are small (a few to a few tens of channels a layer): split over the cores
    inside one call, their convolutions wait for each other at every layer; as separate calls of one
    thread each they do not. An onnxruntime session takes calls from several threads at once, so a
    request's batches (the pose network's views and slices, the localiser's slices) go to
    ``workers`` threads (:class:`~service.core.threads.ProcessThreads`) that call one session opened
    with one intra-op thread (:meth:`options`): the same numbers, in about 0.8-0.85 of the time on
    two cores (``benchmarks/onnx_calls_bench.py``). ``workers`` 0 means every core this process may
    use (:func:`~service.core.machine.usable_cores`); 1 runs the calls one after the other.
    """

    def __init__(self, workers: int = 0) -> None:
        self.threads = ProcessThreads(workers or usable_cores(), "svrnet-onnx")

    @property
    def workers(self) -> int:
        """How many calls run at once."""
        return self.threads.workers

    @staticmethod
    def options() -> ort.SessionOptions:
        """The session options of a model whose calls run side by side: one intra-op thread a call."""
        return session_options(1)

    def map(self, call: Callable[[T], R], items: Iterable[T]) -> list[R]:
        """``[call(item) for item in items]``, the calls on :attr:`workers` threads, in order."""
        return self.threads.map(call, items)
