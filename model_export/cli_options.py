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
