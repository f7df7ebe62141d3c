"""ONNX export: real MC dropout in onnxruntime, parity with PyTorch, metadata, the whole pipeline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from model_export.export import build_metadata, count_random_nodes, export_onnx, fix_draws
from model_export.model import SVRNet
from service.geometry import encodings
from service.inference.estimator import OnnxPoseEstimator
from service.inference.views import SHIPPED_VIEWS
from service.inference.model_file import load_model
from tests.support.pose_models import tiny_pose_model

SIZE = 64


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[SVRNet, Path]:
    torch.manual_seed(0)
    model = tiny_pose_model(SIZE, [torch.rand(16, 1, SIZE, SIZE) * 255 for _ in range(3)])
    meta = build_metadata(model, name="tiny", version="0.0.1", pixel_mm=2.0, variance_threshold=12.5,
                          atlas_id="phantom", training_data="none", licences="n/a")
    path = export_onnx(model, tmp_path_factory.mktemp("onnx") / "tiny.onnx", meta)
    return model, path


def inputs(n: int, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random((n, 1, SIZE, SIZE)) * 255).astype(np.float32)


def test_graph_keeps_one_random_node_per_dropout_layer(exported: tuple[SVRNet, Path]) -> None:
    assert count_random_nodes(exported[1]) == 2  # before the shared FC and before the branch FCs
    import onnx

    ops = {n.op_type for n in onnx.load(str(exported[1])).graph.node}
    assert "Dropout" not in ops and "BatchNormalization" not in ops  # eval-mode export, BN folded


def test_metadata_is_readable_by_the_service(exported: tuple[SVRNet, Path]) -> None:
    m = load_model(exported[1])
    assert (m.info.name, m.info.backbone, m.info.label_type, m.info.input_size) == ("tiny", "compact", "anchor", SIZE)
    assert m.info.pixel_spacing_mm == 2.0 and m.info.variance_threshold == 12.5
    for key in ("intensity", "atlas_id", "training_data", "licences", "commit", "version"):
        assert key in m.info.metadata
    assert len(m.info.sha256) == 64


def test_deterministic_pass_equals_pytorch(exported: tuple[SVRNet, Path]) -> None:
    model, path = exported
    x = inputs(7)
    got = load_model(path).run(x, np.zeros(1, np.float32))[:, 0]
    with torch.no_grad():
        ref = model(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(got, ref, atol=1e-4, rtol=1e-5)


def test_mc_passes_differ_and_match_pytorch_mc_statistics(exported: tuple[SVRNet, Path]) -> None:
    model, path = exported
    x = inputs(2, seed=1)
    n = 3000
    got = load_model(path).run(x, np.ones(n, np.float32))                       # [2, n, 9]
    assert got.shape == (2, n, 9)
    assert np.abs(got[:, 0] - got[:, 1]).max() > 1e-3
    # PyTorch reference: trunk in eval mode, the head's dropout active (nn.functional.dropout).
    model.eval()
    with torch.no_grad():
        feats = model.features(torch.from_numpy(x)).repeat_interleave(n, 0)
        drop = lambda t: torch.nn.functional.dropout(t, model.head.p, True)  # noqa: E731
        ref = (model.head(feats, drop) * model.label_scale + model.label_mean).numpy().reshape(2, n, 9)
    sd = ref.std(axis=1)
    assert (sd > 0.1).all()
    # Means agree within 5 standard errors; spreads within 10 %.
    np.testing.assert_array_less(np.abs(got.mean(1) - ref.mean(1)), 5 * sd * np.sqrt(2 / n) + 1e-6)
    np.testing.assert_allclose(got.std(1), sd, rtol=0.1)


def test_seeded_runs_are_reproducible_while_successive_runs_differ(exported: tuple[SVRNet, Path]) -> None:
    # onnxruntime seeds a random node's generator when the session is created: seed first.
    x = inputs(2, seed=2)
    ort.set_seed(1234)
    model = load_model(exported[1])
    a1, a2 = model.run(x, np.ones(5, np.float32)), model.run(x, np.ones(5, np.float32))
    ort.set_seed(1234)
    b1 = load_model(exported[1]).run(x, np.ones(5, np.float32))
    np.testing.assert_array_equal(a1, b1)
    assert np.abs(a1 - a2).max() > 1e-3


@pytest.fixture(scope="module")
def fixed(exported: tuple[SVRNet, Path]) -> Path:
    """The tiny model with its dropout draws fed by the service (seed 3)."""
    path = exported[1].with_name("tiny-fixed.onnx")
    path.write_bytes(exported[1].read_bytes())
    assert fix_draws(path, seed=3) == 2
    again = path.with_name("tiny-fixed-again.onnx")
    again.write_bytes(path.read_bytes())
    assert fix_draws(again, seed=3) == 2                      # already fixed: the same two layers, counted
    return path


def test_fixed_draws_compute_what_pytorch_computes_with_the_same_draws(exported: tuple[SVRNet, Path], fixed: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    model, m = exported[0], load_model(fixed)
    assert count_random_nodes(fixed) == 0 and [n for n, _ in m.draw_inputs] == ["dropout_uniform_0", "dropout_uniform_1"]
    x = inputs(3, seed=5)
    draws = m.draws(6, draw=2)
    got = m.run(x, np.ones(6, np.float32), draw=2)
    fed = iter(torch.from_numpy(np.array(a)) for a in draws.values())         # the head's layers, in order
    monkeypatch.setattr(torch, "rand_like", lambda like: next(fed).reshape(like.shape))
    with torch.no_grad():
        ref = model.eval().mc_forward(torch.from_numpy(x), torch.ones(6)).numpy()
    np.testing.assert_allclose(got, ref, atol=1e-4, rtol=1e-5)
    assert np.std(got, axis=1).min() > 1e-3                                     # still Monte Carlo


def test_fixed_draws_give_a_slice_one_answer_in_any_request(exported: tuple[SVRNet, Path], fixed: Path) -> None:
    m = load_model(fixed)
    assert m.mc_seed == 3 and m.info.metadata["version"] == load_model(exported[1]).info.metadata["version"]
    x = inputs(9, seed=6)[:, 0]
    est = OnnxPoseEstimator(m, batch_slices=4)
    whole, again, part = est.sample_labels(x, 20), est.sample_labels(x, 20), est.sample_labels(x[5:7], 20)
    np.testing.assert_array_equal(whole, again)
    np.testing.assert_array_equal(whole[5:7], part)                              # batch, stream: the same samples
    # The first n passes of a longer draw are the draw of n; each draw (a test-time view) is its own.
    np.testing.assert_array_equal(m.draws(5)["dropout_uniform_1"], m.draws(300)["dropout_uniform_1"][:, :5])
    assert not np.array_equal(m.draws(5, draw=0)["dropout_uniform_0"], m.draws(5, draw=1)["dropout_uniform_0"])
    fresh = OnnxPoseEstimator(load_model(fixed)).estimate(x, 20)                # another process, the same answer
    np.testing.assert_array_equal(fresh.mean, est.estimate(x, 20).mean)
    other = m.with_seed(4)                                                       # another ensemble, on request
    assert other.mc_seed == 4 and other.session is m.session
    assert np.abs(OnnxPoseEstimator(other).sample_labels(x, 20) - whole).max() > 1e-3
    np.testing.assert_array_equal(OnnxPoseEstimator(other.with_seed(3)).sample_labels(x, 20), whole)


def test_decoded_outputs_are_proper_rotations(exported: tuple[SVRNet, Path]) -> None:
    est = OnnxPoseEstimator(load_model(exported[1]), batch_slices=4)
    labels = est.sample_labels(inputs(9)[:, 0], 20)
    assert labels.shape == (9, 20, 9)
    r = encodings.decode("anchor", labels.astype(np.float64))[..., :3, :3]
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-9)
    result = est.estimate(inputs(9)[:, 0], 20)
    assert result.mean.shape == (9, 4, 4) and (result.variance > 0).all()


def test_tiny_pipeline_trains_exports_and_loads(phantom_atlas: Path, tmp_path: Path) -> None:
    from model_export.packaging import export_checkpoint
    from model_export.train import train
    from model_export.train_config import TrainConfig

    cfg = TrainConfig(backbone="compact", width=0.25, steps=6, batch=16, lr=1e-3, val_every=3, val_per_volume=4,
                      reuse=2, pool=3, hidden=32, simulation=dict(size=48, pixel_mm=2.5))
    best = train(cfg, tmp_path / "run", phantom_atlas, progress=False)
    assert best.exists() and (tmp_path / "run" / "loss.png").exists()
    log = (tmp_path / "run" / "log.csv").read_text().splitlines()
    assert log[0].startswith("step,samples") and len(log) >= 3
    onnx_path = export_checkpoint(best, tmp_path / "m.onnx", name="t", version="0", variance_threshold=5.0)
    m = load_model(onnx_path)
    assert m.info.input_size == 48 and m.info.pixel_spacing_mm == 2.5
    assert m.info.tta_views == SHIPPED_VIEWS          # served as `ship` serves: no export runs one view by default
    assert m.run(np.zeros((1, 48, 48), np.float32), np.ones(3, np.float32)).shape == (1, 3, 9)
    # Resume continues from the checkpoint's step.
    cfg.steps = 9
    train(cfg, tmp_path / "run", phantom_atlas, resume=tmp_path / "run" / "last.pt", progress=False)
    assert (tmp_path / "run" / "log.csv").read_text().splitlines()[-1].startswith("9,")
    # A second stage starts from the weights with a fresh schedule; samples and time are totals.
    import torch

    first = torch.load(tmp_path / "run" / "last.pt", weights_only=False)
    stage = TrainConfig(**{**cfg.__dict__, "steps": 3, "val_every": 3})
    train(stage, tmp_path / "stage2", phantom_atlas, init=tmp_path / "run" / "last.pt", progress=False)
    second = torch.load(tmp_path / "stage2" / "last.pt", weights_only=False)
    assert second["step"] == 3 and second["samples_seen"] == first["samples_seen"] + 3 * 16
    assert second["config"]["init_from"]["steps"] == 9 and second["scheduler"]["milestones"]
    with pytest.raises(ValueError, match="differs"):
        train(TrainConfig(**{**stage.__dict__, "hidden": 64}), tmp_path / "bad", phantom_atlas,
              init=tmp_path / "run" / "last.pt", progress=False)
    # (after the training runs: their loader forks workers, which onnxruntime's threads must not precede)
    # The evaluation report's command regenerates it: the options it ran with, not the defaults.
    from model_export.evaluate import evaluate

    evaluate(onnx_path, tmp_path / "report.md", phantom_atlas, per_volume=2, mc_samples=3)
    command = (tmp_path / "report.md").read_text().split("Regenerate with\n`", 1)[1].split("`", 1)[0]
    assert command.endswith(f"--per-volume 2 --mc-samples 3 --root {phantom_atlas}") and "--seed" not in command


def test_a_grid_model_exports_and_the_service_decodes_it(tmp_path: Path) -> None:
    """The grid label through ONNX and the service's statistics: 192 outputs, proper mean poses."""
    torch.manual_seed(1)
    model = SVRNet("compact", 0.25, "grid", SIZE, hidden=32, dropout=0.25)
    model.set_label_normalisation(torch.from_numpy(encodings.encode("grid", np.stack([np.eye(4)] * 2))).float()
                                  + torch.randn(2, 192) * 30)
    model.eval()
    meta = build_metadata(model, name="g", version="0", pixel_mm=2.0, variance_threshold=1.0, atlas_id="p",
                          training_data="none", licences="n/a", symmetry_plane_x_mm=0.5)
    path = export_onnx(model, tmp_path / "g.onnx", meta)
    m = load_model(path)
    assert m.info.label_type == "grid" and m.info.symmetry_plane_x_mm == 0.5
    assert m.run(inputs(2)[:, 0], np.ones(4, np.float32)).shape == (2, 4, 192)
    est = OnnxPoseEstimator(m).estimate(inputs(3)[:, 0], 10)
    rot = est.mean[:, :3, :3]
    assert np.allclose(np.linalg.det(rot), 1.0) and np.all(np.isfinite(est.variance))
    with torch.no_grad():
        ref = model(torch.from_numpy(inputs(3))).double().numpy()
    det = OnnxPoseEstimator(m).sample_labels(inputs(3)[:, 0], 0)[:, 0]
    assert np.allclose(det, ref, atol=1e-3)


def test_error_shape_metadata_round_trips_and_bad_values_are_refused(exported: tuple[SVRNet, Path], tmp_path: Path) -> None:
    import shutil

    from model_export.spread import write_metadata

    path = tmp_path / "shaped.onnx"
    shutil.copy(exported[1], path)
    assert load_model(path).info.mc_error_shape is None                    # not calibrated: alike in all
    write_metadata(path, {"mc_error_shape": "3.8,0.5,0.2,0.03,0.13,1.3"})
    assert load_model(path).info.mc_error_shape == (3.8, 0.5, 0.2, 0.03, 0.13, 1.3)
    assert load_model(path).info.mc_error_depth_gain == 0.0
    write_metadata(path, {"mc_error_depth_gain": "1.8"})
    assert load_model(path).info.mc_error_depth_gain == 1.8
    for bad in ("1,2,3", "1,1,1,1,1,0", "a,b,c,d,e,f"):
        write_metadata(path, {"mc_error_shape": bad})
        with pytest.raises(ValueError, match="metadata"):
            load_model(path)
