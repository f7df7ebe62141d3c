"""ONNX export of a trained localiser, with the facts the service and the model card need.

The graph takes ``stacks [n, 3, H, W]`` float32 (:func:`~service.preprocess.localiser_inputs.localiser_inputs`;
``H`` and ``W`` multiples of 16, any ``n``) and gives ``logits [n, 1, H, W]``. ``metadata_props``
carry ``grid_mm`` (the network grid), the version, the training data and their licences.
"""

from __future__ import annotations

from pathlib import Path

import torch

from model_export.atlas import POPULATIONS
from model_export.localiser import GRID_MM
from model_export.localiser.net import LocaliserNet
from model_export.training_record import git_commit

INPUT, OUTPUT = "stacks", "logits"


def load_checkpoint(path: Path) -> LocaliserNet:
    """The network of a training checkpoint, in eval mode."""
    state = torch.load(path, map_location="cpu", weights_only=False)  # our own checkpoint
    net = LocaliserNet(**state["config"])
    net.load_state_dict(state["model"])
    return net.eval()


def checkpoint_grid_mm(checkpoint: Path, given: float | None = None) -> float:
    """The network grid of ``checkpoint``: the one its training shards were made on, which it records;
    ``given`` where it records none (:data:`GRID_MM` where neither says).

    Raises:
        ValueError: ``given`` differs from the grid the checkpoint records (the service would resample
            every stack to a grid the network never saw).
    """
    recorded = torch.load(checkpoint, map_location="cpu", weights_only=False).get("grid_mm")  # our own checkpoint
    if recorded is not None and given is not None and abs(float(recorded) - float(given)) > 1e-9:
        raise ValueError(f"grid_mm: {checkpoint} was trained on shards of a {recorded} mm grid, not {given} mm")
    return float(recorded if recorded is not None else GRID_MM if given is None else given)


def export_onnx(checkpoint: Path, out: Path, *, grid_mm: float | None = None, version: str,
                extra: dict | None = None) -> Path:
    """Write the ONNX file of ``checkpoint`` with its metadata (its grid: :func:`checkpoint_grid_mm`
    of ``grid_mm``); returns ``out``."""
    import onnx                            # here: training imports this module, and a training host may lack it

    grid_mm = checkpoint_grid_mm(checkpoint, grid_mm)
    net = load_checkpoint(checkpoint)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    x = torch.zeros(2, net.config["in_channels"], 64, 64)
    torch.onnx.export(net, x, str(out), input_names=[INPUT], output_names=[OUTPUT], opset_version=17,
                      dynamic_axes={INPUT: {0: "n", 2: "h", 3: "w"}, OUTPUT: {0: "n", 2: "h", 3: "w"}}, dynamo=False)
    model = onnx.load(str(out))
    meta = {"name": "svrnet-localiser", "version": version, "grid_mm": grid_mm, "architecture":
            f"2.5D U-Net, width {net.config['width']}, depth {net.config['depth']}",
            "inputs": f"{INPUT}[n,3,H,W] float32: a slice between its neighbours, /p99.5 of the stack, {grid_mm} mm pixels",
            "outputs": f"{OUTPUT}[n,1,H,W] float32: brain (intracranial) logit per pixel",
            "training_data": "synthetic whole-uterus stacks around the atlas brains (model_export.localiser.scenes)",
            "licences": "; ".join(POPULATIONS.values()), "commit": git_commit(), **(extra or {})}
    for key, value in meta.items():
        model.metadata_props.append(onnx.StringStringEntryProto(key=key, value=str(value)))
    onnx.save(model, str(out))
    return out
