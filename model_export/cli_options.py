"""Options the ``svrnet-train`` commands share."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def given(ctx: typer.Context, param: typer.CallbackParam) -> bool:
    """Whether the option was given (on the command line or by its variable), not left at its default.
    Typer ships its own copy of click, whose ``ParameterSource`` is not ``click.core``'s: compared by name."""
    source = ctx.get_parameter_source(param.name)
    return source is not None and source.name != "DEFAULT"


def atlas_root(ctx: typer.Context, param: typer.CallbackParam, root: Path) -> Path:
    """A ``--root`` given that holds no atlas volumes (nor a packed folder) is refused at once by name,
    not with a traceback after the run folder is made (the default is checked where it is read)."""
    from model_export.atlas import list_volumes

    if not given(ctx, param):
        return root
    try:
        list_volumes(root)
    except FileNotFoundError as missing:
        raise typer.BadParameter(str(missing)) from None
    return root


Root = Annotated[Path, typer.Option(help="folder holding crl_sta/ and spina_bifida_cc0/, or a packed folder",
                                    callback=atlas_root)]


def validation_root(ctx: typer.Context, param: typer.CallbackParam, root: Path) -> Path:
    """:func:`atlas_root` for the commands that measure on the validation volumes (evaluate, calibrate,
    ship): a folder without them (``pack --training-only``'s) is refused at once by name."""
    from model_export.atlas import split

    root = atlas_root(ctx, param, root)
    if not given(ctx, param):
        return root
    try:
        split(root)
    except ValueError as missing:
        raise typer.BadParameter(f"{root}: {missing}; these commands measure on them (a folder of `pack` "
                                 "without --training-only holds them)") from None
    return root


ValidationRoot = Annotated[Path, typer.Option(help="folder holding crl_sta/ and spina_bifida_cc0/, or a packed "
                                                   "folder with the validation volumes", callback=validation_root)]


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
                                 "ship` takes those)")
    return path


PoseCheckpoint = Annotated[Path, typer.Argument(callback=pose_checkpoint, help="a checkpoint of svrnet-train train")]


def pose_model(path: Path | None) -> Path | None:
    """An exported pose model (``svrnet-train export``'s or a shipped ``model.onnx``), else a usage error
    naming it: a path that is not there, a file onnxruntime cannot open, or a model without a pose
    network's metadata (a localiser's) is refused in one line before any work."""
    from service.inference.model_file import load_model

    if path is None:
        return None
    if not path.is_file():
        raise typer.BadParameter(f"{path}: no such file")
    try:
        load_model(path)
    except Exception as bad:  # noqa: BLE001 - onnxruntime's and the metadata's errors on a file that is no pose model
        raise typer.BadParameter(f"{path}: not an exported pose model ({type(bad).__name__}; a checkpoint? "
                                 "`svrnet-train export` makes one; a localiser's? its commands are under "
                                 "`svrnet-train localiser`)") from None
    return path


PoseModel = Annotated[Path, typer.Argument(callback=pose_model, help="an exported pose model (model.onnx)")]
