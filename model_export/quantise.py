"""8-bit convolutions for a pose model: the trunk runs mostly in int8, the MC-dropout head stays float.

The trunk's convolutions are nearly all of a request's network time (the head is a few small
matrix products per MC pass). onnxruntime's static quantisation (:func:`quantize_static`, QDQ
format) turns each convolution into ``QuantizeLinear -> QLinearConv -> DequantizeLinear``: int8
weights per output channel, uint8 activations whose ranges are calibrated on simulated training
slices passed through the service's own preprocessing (:class:`~model_export.simulate.SliceSimulator`).
Only ``Conv`` nodes are quantised, so the head's ``RandomUniformLike`` dropout masks, its matrix
products and the label decoding stay in float32 and MC dropout stays stochastic.

The weights use 7 of their 8 bits (``reduce_range``): x86 CPUs without VNNI multiply uint8 by int8
in pairs summed into int16, which saturates with full-range weights and moves the poses several
times more than the lost bit does. The first :data:`FLOAT_CONVS` convolutions stay float: the first
sees one input channel, where an int8 convolution is slower than a float one, and the pair of them
moves a slice's pose more than all the later ones together (docs/reports/training-runs.md, "int8 convolutions").

The quantised file keeps every metadata entry of its source (the calibration of the spread and of
the accept flags included) and adds ``quantised``, which names the scheme and its calibration set:
the service reads such a file as any other.

    .venv/bin/svrnet-train quantise service/models/default/model.onnx /tmp/model-int8.onnx
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import onnx
from numpy.typing import NDArray
from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
from onnxruntime.quantization.shape_inference import quant_pre_process

from model_export.atlas import DEFAULT_ATLAS_ROOT, VALIDATION_VOLUMES, load_volumes, split, validation_volumes
from model_export.export import INPUT_PASSES, INPUT_SLICES, count_random_nodes, metadata_of, set_metadata
from model_export.simulate import SimulationConfig, SliceSimulator
from service.inference.model_file import load_model

CALIBRATION_SLICES = 1024
FLOAT_CONVS = 2
"""Leading convolutions (in graph order) that stay float."""
BATCH = 64


def calibration_slices(count: int = CALIBRATION_SLICES, seed: int = 0, root: Path = DEFAULT_ATLAS_ROOT,
                       size: int = 96, pixel_mm: float = 1.25,
                       held_out: Sequence[str] = VALIDATION_VOLUMES) -> NDArray[np.float32]:
    """``[count, 1, size, size]`` preprocessed slices of the training volumes (those of ``root`` not
    ``held_out``), corrupted as in training, on the model's grid (``size`` pixels of ``pixel_mm``)."""
    config = SimulationConfig(size=size, pixel_mm=pixel_mm)
    simulator = SliceSimulator(load_volumes(split(root, held_out)[0], root), config)
    rng = np.random.default_rng(seed)
    parts, have = [], 0
    while have < count:
        batch = simulator.batch(min(BATCH, count - have), rng).inputs
        if not len(batch):
            raise ValueError(f"calibration_slices: no slice of {root} keeps enough of its brain mask")
        parts.append(batch)
        have += len(batch)
    return np.concatenate(parts)[:count, None].astype(np.float32)


def quantise_model(source: Path, out: Path, count: int = CALIBRATION_SLICES, seed: int = 0,
                   root: Path = DEFAULT_ATLAS_ROOT) -> Path:
    """:func:`quantise` with ``count`` :func:`calibration_slices` on the grid ``source``'s metadata gives,
    none of the model's validation volumes among them."""
    info = load_model(source).info
    return quantise(source, out, calibration_slices(count=count, seed=seed, root=root, size=info.input_size,
                                                    pixel_mm=info.pixel_spacing_mm,
                                                    held_out=validation_volumes(info.metadata)))


class _Slices(CalibrationDataReader):
    """Feeds the calibration slices to onnxruntime's calibrator in batches, each with one MC pass (and
    its dropout draws, for a model that takes them as inputs)."""

    def __init__(self, slices: NDArray[np.float32], draws: dict[str, NDArray[np.float32]]) -> None:
        self._batches: Iterator[NDArray[np.float32]] = iter(np.array_split(slices, max(1, len(slices) // BATCH)))
        self._draws = draws

    def get_next(self) -> dict[str, NDArray[np.float32]] | None:
        x = next(self._batches, None)
        return None if x is None else {INPUT_SLICES: np.ascontiguousarray(x), INPUT_PASSES: np.ones(1, np.float32),
                                       **self._draws}


def quantise(source: Path, out: Path, slices: NDArray[np.float32], float_convs: int = FLOAT_CONVS) -> Path:
    """Write ``source`` with int8 convolutions to ``out`` (which may be ``source``), activation ranges
    calibrated on ``slices``.

    Raises:
        ValueError: ``source`` is quantised already, or the quantised graph lost dropout's random nodes
            or draw inputs (MC dropout would stop being stochastic).
    """
    source, out = Path(source), Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = metadata_of(onnx.load(str(source)))
    if "quantised" in meta:
        raise ValueError(f"{source} is quantised already ({meta['quantised']})")
    random_nodes, model = count_random_nodes(source), load_model(source)
    with tempfile.TemporaryDirectory() as tmp:
        prepared = Path(tmp) / "prepared.onnx"
        quant_pre_process(str(source), str(prepared), skip_symbolic_shape=True)
        convs = [n.name for n in onnx.load(str(prepared)).graph.node if n.op_type == "Conv"]
        reader = _Slices(slices, model.draws(1))
        quantize_static(str(prepared), str(out), reader, quant_format=QuantFormat.QDQ, per_channel=True,
                        op_types_to_quantize=["Conv"], nodes_to_exclude=convs[:float_convs],
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        calibrate_method=CalibrationMethod.MinMax, reduce_range=True)
    meta["quantised"] = (f"int8 convolutions after the first {float_convs} of {len(convs)} (onnxruntime QDQ, 7-bit "
                         f"per-channel weights, activation ranges of {len(slices)} simulated training slices); "
                         "head and dropout float32")
    proto = onnx.load(str(out))
    set_metadata(proto, meta)
    onnx.save(proto, str(out))
    if count_random_nodes(out) != random_nodes or load_model(out).draw_inputs != model.draw_inputs:
        raise ValueError(f"{out}: quantisation removed dropout's random nodes or draw inputs")
    return out
