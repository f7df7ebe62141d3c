"""int8 convolutions: the trunk quantised, the MC-dropout head still float and stochastic, metadata kept."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from model_export.export import build_metadata, count_random_nodes, export_onnx, fix_draws
from model_export.quantise import FLOAT_CONVS, calibration_slices, quantise
from service.geometry import anchors, encodings
from service.inference.model_file import load_model
from tests.support.pose_models import tiny_pose_model

SIZE = 64


def phantom_slices(n: int, seed: int) -> np.ndarray:
    """Bright discs of random radius and centre on black, 0-255, as the preprocessing leaves slices."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:SIZE, :SIZE]
    cy, cx, r = rng.uniform(24, 40, (3, n, 1, 1))
    r = r / 2.0
    inside = (yy - cy) ** 2 + (xx - cx) ** 2 < r ** 2 * 4
    return (inside * rng.uniform(80, 255, (n, 1, 1)) + rng.normal(0, 3, (n, SIZE, SIZE))).clip(0, 255)[:, None].astype(np.float32)


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    model = tiny_pose_model(SIZE, [torch.from_numpy(phantom_slices(16, 1))] * 3)
    meta = build_metadata(model, name="tiny", version="0.0.1", pixel_mm=2.0, variance_threshold=12.5,
                          atlas_id="phantom", training_data="none", licences="n/a", extra={"max_expected_error_mm": 4.5})
    folder = tmp_path_factory.mktemp("quantise")
    source = export_onnx(model, folder / "fp32.onnx", meta)
    return source, quantise(source, folder / "int8.onnx", phantom_slices(128, 2))


def test_convolutions_run_in_int8_and_the_head_stays_float(pair: tuple[Path, Path]) -> None:
    source, quantised_path = pair
    ops = [n.op_type for n in onnx.load(str(quantised_path)).graph.node]
    convs = sum(n.op_type == "Conv" for n in onnx.load(str(source)).graph.node)
    quantised = convs - FLOAT_CONVS
    assert ops.count("Conv") == convs and ops.count("QuantizeLinear") >= 2 * quantised   # weights and inputs
    first = [n for n in onnx.load(str(quantised_path)).graph.node if n.op_type == "Conv"][0]
    assert not first.input[1].endswith("DequantizeLinear_Output")                         # stays float
    assert count_random_nodes(quantised_path) == count_random_nodes(source) == 2
    assert "MatMul" in ops or "Gemm" in ops                                        # the head is not quantised


def test_metadata_and_calibration_are_kept_and_the_scheme_named(pair: tuple[Path, Path]) -> None:
    before, after = load_model(pair[0]).info, load_model(pair[1]).info
    assert {k: v for k, v in after.metadata.items() if k != "quantised"} == before.metadata
    assert "int8" in after.metadata["quantised"] and "128" in after.metadata["quantised"]
    assert after.variance_threshold == before.variance_threshold and after.sha256 != before.sha256


def test_a_quantised_model_is_not_quantised_again(pair: tuple[Path, Path], tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="quantised already"):
        quantise(pair[1], tmp_path / "twice.onnx", phantom_slices(8, 4))
    assert not (tmp_path / "twice.onnx").exists()


def test_poses_stay_near_the_float_model_and_mc_stays_stochastic(pair: tuple[Path, Path]) -> None:
    x = phantom_slices(32, 3)
    fp32, int8 = load_model(pair[0]), load_model(pair[1])
    det = [encodings.decode("anchor", m.run(x, np.zeros(1, np.float32))[:, 0].astype(np.float64)) for m in (fp32, int8)]
    moved = anchors.ed(det[0], det[1])
    spread = anchors.ed(det[0], det[0][::-1])                       # how far apart two slices' poses lie
    assert np.median(moved) < 0.1 * np.median(spread)
    mc = int8.run(x[:4], np.ones(20, np.float32))
    assert mc.shape[:2] == (4, 20) and np.std(mc, axis=1).min() > 0    # every slice's samples differ


def test_a_model_with_fixed_draws_quantises_and_keeps_them(pair: tuple[Path, Path], tmp_path: Path) -> None:
    source = tmp_path / "fixed.onnx"
    source.write_bytes(pair[0].read_bytes())
    fix_draws(source)
    out = load_model(quantise(source, tmp_path / "fixed-int8.onnx", phantom_slices(32, 5)))
    assert out.draw_inputs == load_model(source).draw_inputs and out.mc_seed == 0
    x = phantom_slices(4, 6)
    np.testing.assert_array_equal(out.run(x, np.ones(8, np.float32)), out.run(x, np.ones(8, np.float32)))


def test_calibration_slices_are_the_training_slices_on_the_model_grid(phantom_atlas: Path) -> None:
    x = calibration_slices(40, seed=0, root=phantom_atlas, size=SIZE, pixel_mm=2.0)
    assert x.shape == (40, 1, SIZE, SIZE) and x.dtype == np.float32
    assert 0.0 <= x.min() and x.max() <= 255.5 and (x.reshape(40, -1).max(1) > 100).all()
