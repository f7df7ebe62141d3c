"""Distillation: the pruned start is the teacher's strongest channels, the target is the mirrored
pass, the loss mixes teacher and truth, and a distilled run trains a narrower network."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from model_export.localiser.distil import distillation_loss, mirrored_logits, pruned
from model_export.localiser.net import LocaliserNet
from model_export.localiser.train import loss_fn


def _teacher(seed: int = 0) -> LocaliserNet:
    torch.manual_seed(seed)
    net = LocaliserNet(width=4, depth=2)
    with torch.no_grad():                                   # distinct batch-norm scales and statistics
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.weight.copy_(torch.rand(m.num_features) + 0.1)
                m.running_mean.copy_(torch.randn(m.num_features) * 0.1)
    return net.eval()


def test_a_pruned_network_of_the_same_width_is_the_teacher() -> None:
    teacher = _teacher()
    x = torch.rand(2, 3, 16, 16)
    with torch.no_grad():
        assert torch.allclose(pruned(teacher, 4).eval()(x), teacher(x), atol=1e-5)


def test_pruning_keeps_the_channels_of_largest_scale() -> None:
    teacher = _teacher()
    with torch.no_grad():
        teacher.down[0][4].weight.copy_(torch.tensor([0.01, 5.0, 0.02, 3.0]))
    student = pruned(teacher, 2)
    assert student.config["width"] == 2
    assert torch.allclose(student.down[0][4].weight, torch.tensor([5.0, 3.0]))     # channels 1 and 3, in order
    assert torch.allclose(student.head.weight[0, :, 0, 0], teacher.head.weight[0, [1, 3], 0, 0])
    assert student(torch.zeros(1, 3, 16, 16)).shape == (1, 1, 16, 16)


def test_the_mirrored_target_is_symmetric_under_the_mirror() -> None:
    teacher = _teacher()
    x = torch.rand(2, 3, 16, 16)
    out = mirrored_logits(teacher, x)
    assert torch.allclose(mirrored_logits(teacher, x.flip(-1)), out.flip(-1), atol=1e-5)
    with torch.no_grad():
        assert not torch.allclose(teacher(x), out, atol=1e-3)       # a random network is not symmetric


def test_the_loss_moves_from_truth_to_teacher_with_its_weight() -> None:
    logits = torch.full((1, 1, 4, 4), 3.0)
    teacher = torch.full((1, 1, 4, 4), 3.0)
    truth = torch.zeros(1, 1, 4, 4)
    losses = [float(distillation_loss(logits, teacher, truth, w, loss_fn)) for w in (0.0, 0.5, 1.0)]
    assert losses[0] == pytest.approx(float(loss_fn(logits, truth)))
    assert losses[0] > losses[1] > losses[2]                         # the teacher agrees, the truth does not


def test_a_distilled_run_trains_a_narrower_network(shards: Path, tmp_path: Path) -> None:
    from model_export.localiser.train import train

    teacher_ckpt, student_ckpt = tmp_path / "teacher.pt", tmp_path / "student.pt"
    train(shards, teacher_ckpt, 0.02, width=4, depth=2, batch=4, crop=32, threads=1)
    train(shards, student_ckpt, 0.03, width=2, depth=2, batch=4, crop=32, threads=1,
          init=teacher_ckpt, teacher=teacher_ckpt, teacher_weight=0.7)
    state = torch.load(student_ckpt, weights_only=False)
    assert state["config"]["width"] == 2 and state["step"] > 0
    assert np.isfinite([float(v.float().abs().sum()) for v in state["model"].values()]).all()


def test_a_fine_tune_with_frozen_norm_keeps_the_running_statistics(shards: Path, tmp_path: Path) -> None:
    from model_export.localiser.train import train

    start = tmp_path / "start.pt"
    train(shards, start, 0.02, width=4, depth=2, batch=4, crop=32, threads=1)
    stats = lambda path: {k: v for k, v in torch.load(path, weights_only=False)["model"].items()  # noqa: E731
                          if k.endswith(("running_mean", "running_var"))}
    moved = {}
    for freeze in (True, False):
        out = tmp_path / f"tuned-{freeze}.pt"
        train(shards, out, 0.01, width=4, depth=2, batch=4, crop=32, threads=1, init=start, lr=1e-3,
              teacher=start, teacher_weight=1.0, freeze_norm=freeze)
        before, after = stats(start), stats(out)
        assert torch.load(out, weights_only=False)["step"] > 0
        moved[freeze] = max(float((after[k] - before[k]).abs().max()) for k in before)
    assert moved[True] == 0.0 and moved[False] > 1e-4


def test_a_network_that_learnt_the_mirrored_pass_runs_once_in_the_service(tmp_path: Path) -> None:
    from model_export.localiser.export import export_onnx
    from service.preprocess.localise import Localiser

    net = _teacher()
    ckpt = tmp_path / "net.pt"
    torch.save({"model": net.state_dict(), "config": net.config}, ckpt)
    x = np.random.default_rng(2).random((3, 3, 16, 16), np.float32)
    with torch.no_grad():
        once = net(torch.from_numpy(x))[:, 0].numpy()
        averaged = mirrored_logits(net, torch.from_numpy(x))[:, 0].numpy()
    for mirrored_pass, expected in (("learnt", once), ("run", averaged), (None, averaged)):
        extra = {} if mirrored_pass is None else {"mirrored_pass": mirrored_pass}
        path = export_onnx(ckpt, tmp_path / f"{mirrored_pass}.onnx", grid_mm=4.0, version="0", extra=extra)
        loc = Localiser.load(path)
        assert loc.mirrored == (mirrored_pass != "learnt")
        assert np.allclose(loc._logits("stacks", x), expected, atol=1e-4)
