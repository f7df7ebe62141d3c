"""Point losses: plain, min over the twins, and mirror-invariant by construction."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from model_export.losses import check_label_type, point_loss, twin_points
from model_export.model import multi_loss
from service.geometry import encodings, iterators, twin

PLANE = 0.7


def _labels(label_type: str, n: int = 16, seed: int = 0) -> tuple[torch.Tensor, np.ndarray]:
    poses = iterators.random_poses(n, np.random.default_rng(seed), tz_max_mm=20.0, centre=np.array([PLANE, 3.0, -2.0]))
    return torch.from_numpy(encodings.encode(label_type, poses)), poses


def test_twin_points_matches_the_numeric_core() -> None:
    lab, poses = _labels("grid")
    want = encodings.encode("grid", twin.twin(poses, PLANE))
    assert np.allclose(twin_points(lab, PLANE).numpy(), want)


def test_l2_is_the_shipped_multi_loss_for_anchors() -> None:
    y, _ = _labels("anchor")
    pred = y + torch.randn_like(y) * 5.0
    mean, scale = y.mean(0), y.std(0)
    want, _ = multi_loss((pred - mean) / scale, (y - mean) / scale, "anchor")
    assert torch.isclose(point_loss(pred, y, mean, scale, "l2").mean(), want)


@pytest.mark.parametrize("label_type", ["anchor", "grid"])
def test_mirror_aware_losses_vanish_on_both_twins_only(label_type: str) -> None:
    y, _ = _labels(label_type)
    tw = twin_points(y, PLANE)
    mean, scale = y.mean(0), y.std(0) + 1.0
    for kind in ("min", "invariant"):
        assert point_loss(y, y, mean, scale, kind, PLANE).max() < 1e-2
        assert point_loss(tw, y, mean, scale, kind, PLANE).max() < 1e-2
        wrong = y + torch.tensor([0.0, 0.0, 10.0]).repeat(y.shape[1] // 3)      # shifted in z
        assert point_loss(wrong, y, mean, scale, kind, PLANE).min() > 0.1
    assert point_loss(tw, y, mean, scale, "l2", PLANE).min() > 0.1


def test_invariant_loss_is_continuous_where_the_twins_meet() -> None:
    """A mid-sagittal target (x = x0 everywhere): the min switches branch there, the invariant does not."""
    y, _ = _labels("grid", n=1)
    y[:, 0::3] = PLANE
    mean, scale = torch.zeros(y.shape[1]), torch.full((y.shape[1],), 10.0)
    eps = torch.linspace(-1.0, 1.0, 41)[:, None]
    pred = y.repeat(41, 1)
    pred[:, 0::3] += eps * torch.linspace(-1.0, 1.0, y.shape[1] // 3)            # a tilt of the predicted plane
    pred.requires_grad_(True)
    inv = point_loss(pred, y.repeat(41, 1), mean, scale, "invariant", PLANE)
    grad = torch.autograd.grad(inv.sum(), pred)[0]
    assert torch.all(torch.isfinite(grad))
    assert torch.all(inv[1:] - inv[:-1] < 0.05)                                  # no jumps
    assert torch.allclose(inv, inv.flip(0), atol=1e-5)                           # +tilt and -tilt are twins


def test_mirror_aware_fit_picks_a_twin_where_l2_averages_them() -> None:
    """Free outputs fit to targets that are the label or its twin at random: l2 learns the average."""
    y, _ = _labels("anchor", n=1, seed=3)
    y[:, 0::3] += 25.0                                       # well off the plane: the twins are far apart
    gen = torch.Generator().manual_seed(0)
    mean, scale = torch.zeros(9), torch.full((9,), 20.0)
    results = {}
    for kind in ("l2", "min", "invariant"):
        middle = (y + twin_points(y, PLANE)) / 2                  # start between the twins
        p = (middle + 3.0 * torch.randn(y.shape, generator=gen)).clone().requires_grad_(True)
        opt = torch.optim.Adam([p], lr=0.5)
        for _ in range(400):
            flip = torch.rand(32, 1, generator=gen) < 0.5
            target = torch.where(flip, twin_points(y.repeat(32, 1), PLANE), y.repeat(32, 1))
            loss = point_loss(p.repeat(32, 1), target, mean, scale, kind, PLANE).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        p = p.detach()
        d = min(float((p - y).norm()), float((p - twin_points(y, PLANE)).norm())) / 3
        results[kind] = d
    assert results["l2"] > 10.0
    assert results["min"] < 1.5 and results["invariant"] < 1.5


def test_mirror_aware_losses_need_point_labels() -> None:
    check_label_type("euler", "l2")
    with pytest.raises(ValueError, match="point label"):
        check_label_type("euler", "min")
    with pytest.raises(ValueError, match="unknown loss"):
        point_loss(torch.zeros(1, 9), torch.zeros(1, 9), torch.zeros(9), torch.ones(9), "max")
