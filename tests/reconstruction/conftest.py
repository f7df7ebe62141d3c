"""Shared, session-scoped phantom acquisitions of the reconstruction tests."""

from __future__ import annotations

import numpy as np
import pytest

from tests.reconstruction.helpers import Acquisition, make_acquisition


@pytest.fixture(scope="session")
def acquisition() -> Acquisition:
    """Three orthogonal stacks (48 x 48 x 20, 1.5 x 1.5 x 3 mm) of the textured phantom, seed 0."""
    return make_acquisition(0)


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
