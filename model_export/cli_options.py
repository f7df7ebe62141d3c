"""Options the ``svrnet-train`` commands share."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def atlas_root(ctx: typer.Context, param: typer.CallbackParam, root: Path) -> Path:
    """A ``--root`` given that holds no atlas volumes (nor a packed folder) is refused at once by name,
    not with a traceback after the run folder is made (the default is checked where it is read)."""
    from click.core import ParameterSource

    from model_export.atlas import list_volumes

    if ctx.get_parameter_source(param.name) is ParameterSource.DEFAULT:
        return root
    try:
        list_volumes(root)
    except FileNotFoundError as missing:
        raise typer.BadParameter(str(missing)) from None
    return root


Root = Annotated[Path, typer.Option(help="folder holding crl_sta/ and spina_bifida_cc0/, or a packed folder",
                                    callback=atlas_root)]


def pose_checkpoint(path: Path) -> Path:
    """A pose network's checkpoint (``svrnet-train train``'s), else a usage error naming it: a path that
    is not there, or a localiser's checkpoint, is refused in one line before any work."""
    import torch

    if not path.is_file():
        raise typer.BadParameter(f"{path}: no such file")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as bad:  # noqa: BLE001 - torch's errors on a file that is no checkpoint
        raise typer.BadParameter(f"{path}: not a torch checkpoint ({type(bad).__name__})") from None
    if not isinstance(saved, dict) or "model_config" not in saved:
        raise typer.BadParameter(f"{path}: not a pose network's checkpoint (a localiser's? `svrnet-train localiser "
                                 "export` takes those)")
    return path


PoseCheckpoint = Annotated[Path, typer.Argument(callback=pose_checkpoint, help="a checkpoint of svrnet-train train")]
