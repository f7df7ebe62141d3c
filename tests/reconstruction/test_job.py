"""A reconstruction job refuses a volume too large for its memory before it reconstructs anything."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.errors import InvalidParameter
from service.reconstruction import job
from tests.reconstruction.helpers import Acquisition


def test_a_resolution_too_fine_for_the_slices_field_of_view_fails_before_any_reconstruction(
        acquisition: Acquisition, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(job, "reconstruct_never_worse", lambda *a, **k: pytest.fail("reconstructed"))
    stacks = [(v, m, p, np.ones(len(p), bool)) for (v, m), p in zip(acquisition.stacks, acquisition.truth)]
    with pytest.raises(InvalidParameter, match=r"^resolution_mm: .* at 0.21 mm holds .* ask for 0\.[0-9]+ mm or coarser"):
        job.refine_job(acquisition.slice_set(), stacks, np.full(acquisition.slice_set().n_slices, 2.0),
                       estimator=None, plane_x_mm=0.0, resolution_mm=0.21, svr_iterations=1)
