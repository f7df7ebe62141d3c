"""What every ONNX model of the service shares: its CPU session options and how a
models folder is loaded.

Example:
    >>> session_options(2).intra_op_num_threads
    2
    >>> session_threads(1), session_threads(4, cores=4), session_threads(0, cores=4)
    ((1, False), (4, False), (2, True))
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import onnxruntime as ort

from service.core.errors import UnusableModelFile
from service.core.threads import available_cores

log = logging.getLogger(__name__)
Loaded = TypeVar("Loaded")


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


def load_models(folder: Path, setting: str, load: Callable[[Path], Loaded],
                names: tuple[str, ...] | None = None) -> dict[str, Loaded]:
    """Each ``<name>/model.onnx`` of ``folder`` (:func:`model_files`; ``names``: those alone) opened by
    ``load``, by name.

    Loading the whole folder (a server's start), a subfolder without ``model.onnx`` is named in a
    warning (a model copied without its file); a folder that cannot be listed loads nothing, as an
    empty one. A file that does not load raises :class:`~service.core.errors.UnusableModelFile` naming it and
    ``setting``, the variable that points to the folder, so that the start fails in one line
    rather than with a traceback or a server without the model.

    Example:
        >>> import tempfile
        >>> root = Path(tempfile.mkdtemp())
        >>> (root / "default").mkdir(); _ = (root / "default" / "model.onnx").write_bytes(b"not onnx")
        >>> load_models(root, "SVRNET_MODELS_DIR", lambda p: p.read_bytes())
        {'default': b'not onnx'}
        >>> def refuse(path): raise ValueError("bad\\nmore")
        >>> try:
        ...     load_models(root, "SVRNET_MODELS_DIR", refuse)
        ... except UnusableModelFile as exc:
        ...     print(str(exc).replace(str(root), "ROOT"))
        SVRNET_MODELS_DIR: ROOT/default/model.onnx does not load as a model (ValueError: bad)
    """
    folder = Path(folder)
    try:
        subfolders = sorted(p for p in folder.iterdir() if p.is_dir()) if folder.is_dir() and names is None else []
    except OSError:                              # not to be listed: no model, as the start's checks say
        subfolders = []
    for sub in subfolders:
        if not sub.name.startswith(".") and not (sub / "model.onnx").is_file():
            log.warning("a folder of %s without model.onnx: no model loaded from it", setting, extra={"model": sub.name})
    loaded: dict[str, Loaded] = {}
    for path in model_files(folder):
        if names is not None and path.parent.name not in names:
            continue
        try:
            loaded[path.parent.name] = load(path)
        except Exception as exc:  # noqa: BLE001 - onnxruntime's own errors, missing metadata: one answer
            reason = (str(exc).strip().splitlines() or [""])[0][:200]
            raise UnusableModelFile(f"{setting}: {path} does not load as a model "
                                    f"({type(exc).__name__}: {reason})") from exc
    return loaded


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
