"""A job's submission checks (``service.api.job_submission``) on the files as read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.api.job_submission import check_submission
from service.core.errors import InvalidParameter
from service.io.volume import Volume
from service.pipeline.prepare import StackUpload


def test_a_region_around_the_head_does_not_bound_the_resolution_as_a_brain_would(tmp_path: Path) -> None:
    """The finest resolution a job may ask is bounded by the brain the masks mark; a box drawn around
    the head is not that brain (the localiser finds it inside), so the box's 1,300 ml do not refuse
    0.3 mm, where an ellipsoid brain mask filling the same box does."""
    affine = np.diag([1.0, 1.0, 3.0, 1.0])
    volume = Volume(np.random.default_rng(0).random((120, 120, 40), np.float32) * 100 + 50, affine)
    box = np.zeros((120, 120, 40), np.uint8)
    box[5:115, 5:115, 2:38] = 1
    x, y, z = np.ogrid[:120, :120, :40]
    brain = (((x - 60) / 55) ** 2 + ((y - 60) / 55) ** 2 + ((z - 20) / 18) ** 2 <= 1).astype(np.uint8)
    region = StackUpload("s.nii.gz", volume, Volume(box, affine), "roi.nii.gz")
    assert region.mask_is_region
    check_submission([region], [], None, tmp_path, 0.3)
    with pytest.raises(InvalidParameter, match="resolution_mm"):
        check_submission([StackUpload("s.nii.gz", volume, Volume(brain, affine), "m.nii.gz")], [], None, tmp_path, 0.3)
