"""ONNX export with Monte Carlo dropout that stays stochastic in onnxruntime.

The exported graph is :class:`~model_export.model.MCExport`: inputs ``slices [B, 1, L, L]``
(float32, 0-255) and ``passes [N]`` (float32; 1 = an MC-dropout pass, 0 = a deterministic pass),
output ``labels [B, N, D]``. The trunk runs once per slice, the head ``N`` times.

* The network is exported in eval mode: BatchNorm uses its running statistics (exported in training
  mode it would use batch statistics and shift the MC mean by several standard deviations).
* Dropout masks come from ``RandomUniformLike`` nodes (``torch.rand_like``). onnxruntime's default
  optimiser removes ``Dropout`` nodes even with ``training_mode=True`` (``EliminateDropout``), but
  it cannot remove these: :func:`count_random_nodes` checks them in the saved file.
* The model card facts the service needs travel in ``metadata_props`` (onnxruntime's
  ``custom_metadata_map``).
"""

from __future__ import annotations

from pathlib import Path

import onnx
import torch

from model_export.model import MCExport, SVRNet
from model_export.training_record import git_commit
from service.geometry.anchors import ANCHOR_HALF_SIZE_MM
from service.geometry.twin import DEFAULT_PLANE_X_MM
from service.inference.model_file import DEFAULT_MC_SEED, DRAWS_PREFIX

INPUT_SLICES, INPUT_PASSES, OUTPUT_LABELS = "slices", "passes", "labels"
INTENSITY_CONVENTION = ("0-255: N4-corrected slice, masked, clipped to the 1st/99th percentile inside the mask "
                        "and rescaled; resampled to the model grid centred on the mask centroid")


def build_metadata(model: SVRNet, *, name: str, version: str, pixel_mm: float, variance_threshold: float,
                   atlas_id: str, training_data: str, licences: str, extra: dict | None = None,
                   symmetry_plane_x_mm: float = DEFAULT_PLANE_X_MM) -> dict[str, str]:
    """The metadata stored in the ONNX file (all values strings).

    ``symmetry_plane_x_mm`` is the atlas mid-sagittal plane the model was trained with (its twin);
    ``commit`` the code's at export (:func:`~model_export.training_record.git_commit`, ``-dirty`` with
    uncommitted changes).
    """
    c = model.config
    meta = {
        "name": name, "version": version, "backbone": c["backbone"], "width": c["width"],
        "label_type": c["label_type"], "input_size": c["input_size"], "pixel_spacing_mm": pixel_mm,
        "intensity": INTENSITY_CONVENTION, "atlas_id": atlas_id, "anchor_half_size_mm": ANCHOR_HALF_SIZE_MM,
        "variance_threshold": variance_threshold, "dropout_p": c["dropout"], "training_data": training_data,
        "licences": licences, "commit": git_commit(), "symmetry_plane_x_mm": symmetry_plane_x_mm,
        "inputs": f"{INPUT_SLICES}[B,1,L,L] float32 0-255; {INPUT_PASSES}[N] float32 (1 = MC pass, 0 = deterministic)",
        "outputs": f"{OUTPUT_LABELS}[B,N,D] float32, physical units (mm, rad)",
    }
    meta.update(extra or {})
    return {k: str(v) for k, v in meta.items()}


def metadata_of(proto: onnx.ModelProto) -> dict[str, str]:
    """A model's metadata entries (``metadata_props``) as a dict."""
    return {p.key: p.value for p in proto.metadata_props}


def set_metadata(proto: onnx.ModelProto, metadata: dict[str, object]) -> None:
    """Replace a model's metadata entries with ``metadata`` (values as strings).

    Example:
        >>> proto = onnx.ModelProto()
        >>> set_metadata(proto, {"a": 1}); set_metadata(proto, {**metadata_of(proto), "b": "x"})
        >>> metadata_of(proto)
        {'a': '1', 'b': 'x'}
    """
    del proto.metadata_props[:]
    for key, value in metadata.items():
        proto.metadata_props.add(key=key, value=str(value))


def export_onnx(model: SVRNet, path: Path, metadata: dict[str, str], opset: int = 17) -> Path:
    """Export ``model`` (put in eval mode) with MC dropout kept stochastic; writes ``metadata``."""
    model = model.eval()
    size = int(model.config["input_size"])
    dummy = (torch.zeros(2, 1, size, size), torch.ones(3))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The wrapper must be in eval mode too: the exporter restores the wrapper's mode recursively
    # afterwards, which would leave the wrapped network in training mode.
    torch.onnx.export(
        MCExport(model).eval(), dummy, str(path), input_names=[INPUT_SLICES, INPUT_PASSES], output_names=[OUTPUT_LABELS],
        dynamic_axes={INPUT_SLICES: {0: "batch"}, INPUT_PASSES: {0: "samples"}, OUTPUT_LABELS: {0: "batch", 1: "samples"}},
        opset_version=opset, dynamo=False, do_constant_folding=True,
    )
    proto = onnx.load(str(path))
    set_metadata(proto, metadata)
    onnx.checker.check_model(proto)
    onnx.save(proto, str(path))
    return path


def fix_draws(path: Path, seed: int = DEFAULT_MC_SEED) -> int:
    """Rewrite the model at ``path`` so that its dropout draws are inputs: each ``RandomUniformLike``
    node becomes the input ``dropout_uniform_<k> [1, samples, F]``
    (:data:`~service.inference.model_file.DRAWS_PREFIX`), which the service fills from ``seed``
    (metadata ``mc_seed``, :meth:`~service.inference.model_file.LoadedModel.draws`). The dropout
    stays Monte Carlo; its draws become a fixed ensemble of sub-networks, so one request gives one
    answer. The rest of the graph and its metadata are kept; a file whose draws are inputs already
    gets only its seed. Returns the number of dropout layers whose draws the file now takes as inputs.
    """
    proto = onnx.load(str(path))
    graph = proto.graph
    shapes = {v.name: v for v in onnx.shape_inference.infer_shapes(proto).graph.value_info}
    random = [n for n in graph.node if n.op_type == "RandomUniformLike"]
    for k, node in enumerate(random):
        units = shapes[node.output[0]].type.tensor_type.shape.dim[-1].dim_value
        if not units:
            raise ValueError(f"{path}: the width of dropout layer {k} is not fixed in the graph")
        name = f"{DRAWS_PREFIX}{k}"
        graph.input.append(onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, [1, "samples", units]))
        for consumer in graph.node:
            consumer.input[:] = [name if x == node.output[0] else x for x in consumer.input]
        graph.node.remove(node)
    set_metadata(proto, {**metadata_of(proto), "mc_seed": seed,
                         "mc_draws": "fixed: dropout_uniform_<k> inputs, filled from mc_seed"})
    onnx.checker.check_model(proto)
    onnx.save(proto, str(path))
    return sum(i.name.startswith(DRAWS_PREFIX) for i in graph.input)


def count_random_nodes(path: Path) -> int:
    """Number of random-number nodes in the graph (one per dropout layer of the head)."""
    proto = onnx.load(str(path))
    return sum(n.op_type in ("RandomUniformLike", "RandomUniform", "RandomNormalLike", "Bernoulli")
               for n in proto.graph.node)
