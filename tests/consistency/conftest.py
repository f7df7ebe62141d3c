"""Shared by the image-consistency tests: a phantom acquisition prepared as the server prepares it."""

from __future__ import annotations

import numpy as np
import pytest

from model_export.acquisitions import simulate_acquisition
from model_export.evaluate_acquisitions import prepare_acquisition
from service.consistency.slice_images import StackImages
from service.geometry import se3
from tests.api.conftest import INFO
from tests.support.phantoms import phantom_brain


def prepared_acquisition(n4: bool = True, **corruption: float) -> tuple[list[StackImages], list[np.ndarray]]:
    """Three stacks of the phantom (mild motion), prepared as the server prepares them (``n4``: with
    bias correction), and each stack's true network-frame poses."""
    img, mask, aff = phantom_brain(0)
    corruption = {"size": 64, "pixel_mm": 1.6, **corruption}
    stacks = simulate_acquisition(img, mask, aff, np.random.default_rng(3), "mild", **corruption)
    prepared, truth = prepare_acquisition(stacks, INFO, bias_correction=n4)
    images = [StackImages(p.slices.images, p.slices.masks, p.slices.pixel_mm, p.prepared.input_from_network(),
                          np.ones(len(t), bool)) for p, t in zip(prepared, truth)]
    return images, truth


@pytest.fixture(scope="module")
def acquisition() -> tuple[list[StackImages], list[np.ndarray]]:
    """With Rician noise and a bias field (N4-corrected, as the server does)."""
    return prepared_acquisition()


def disturbed(truth: list[np.ndarray], deg: float, mm: float, seed: int) -> list[np.ndarray]:
    """Each slice's pose moved by its own random error (``deg`` / ``mm`` per coordinate, in its own frame)."""
    rng = np.random.default_rng(seed)
    return [t @ se3.exp(np.concatenate([rng.normal(0, np.radians(deg), (len(t), 3)), rng.normal(0, mm, (len(t), 3))], 1))
            for t in truth]
