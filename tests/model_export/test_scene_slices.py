"""Training slices cut with the localiser's masks: each label is the pose its input was cut at."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from model_export.localiser.scenes import HeadModel
from model_export.scene_slices import ScenePool, scene_slices
from model_export.simulate import sample_slices_torch
from service.core.settings import DEFAULT_LOCALISERS_DIR
from service.geometry import se3
from service.preprocess.localise import Localiser
from tests.support.phantoms import phantom_brain


@pytest.fixture(scope="module")
def head_and_mask() -> tuple[HeadModel, np.ndarray, np.ndarray]:
    image, mask, affine = phantom_brain(11)
    return HeadModel.from_arrays(image, mask, affine), mask.astype(np.float32), affine


@pytest.fixture(scope="module")
def localiser() -> Localiser:
    return Localiser.load(DEFAULT_LOCALISERS_DIR / "default" / "model.onnx", threads=1)


def _brain_at(mask: np.ndarray, affine: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """The phantom's brain mask cut at ``poses`` on the network's grid (96 px of 1.25 mm)."""
    volume = torch.from_numpy(mask)[None, None]
    return sample_slices_torch(volume, affine, poses, 96, 1.25)[:, 0].numpy() > 0.5


def _dice(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2 * (a & b).sum((1, 2)) / np.maximum(a.sum((1, 2)) + b.sum((1, 2)), 1)


def test_each_label_is_the_pose_its_input_shows(head_and_mask, localiser: Localiser) -> None:  # noqa: ANN001
    """The atlas brain cut at each slice's label covers what the localiser's pose mask left of the
    input (mean Dice over 0.75), better than at the label moved 5 mm either way along either axis of
    the slice's plane (a centring lost or mirrored) or 10 mm along its normal (a label in another
    frame fails all of these)."""
    head, mask, affine = head_and_mask
    batch = scene_slices(head, np.random.default_rng(3), localiser, 96, 1.25)
    assert len(batch.inputs) >= 10 and batch.inputs.shape[1:] == (96, 96)
    seen = batch.inputs > 0

    def cover(twist: list[float]) -> float:
        return float(np.mean(_dice(_brain_at(mask, affine, batch.poses @ se3.exp(np.array(twist))), seen)))

    truth = cover([0.0] * 6)
    assert truth > 0.75
    for moved in ([5, 0, 0], [-5, 0, 0], [0, 5, 0], [0, -5, 0], [0, 0, 10], [0, 0, -10]):
        assert cover([0.0, 0.0, 0.0, *moved]) < truth, moved


def test_a_pool_replaces_its_scenes_as_their_slices_are_drawn(head_and_mask, localiser: Localiser) -> None:  # noqa: ANN001
    """Drawn about ``reuse`` times per slice, a scene is replaced: 2 scenes of about 20 slices,
    reuse 1, 16 slices a draw: within 6 draws (96 slices) the pool holds a new scene, and the draw
    after that takes from it. The draws stop there: a new scene is never replaced by an old one, so
    the later draws (a 2-3 s scene each) could not undo what was seen."""
    head, _, _ = head_and_mask
    pool = ScenePool([head], localiser, 96, 1.25, np.random.default_rng(4), scenes=2, reuse=1.0)
    first = list(pool.pool)                      # held: a replaced scene's id cannot pass to its successor
    replaced = False
    for _ in range(6):
        x, poses = pool.draw(16)
        assert x.shape == (16, 96, 96) and poses.shape == (16, 4, 4)
        if replaced:
            break
        replaced = any(all(scene is not old for old in first) for scene in pool.pool)
    assert replaced
