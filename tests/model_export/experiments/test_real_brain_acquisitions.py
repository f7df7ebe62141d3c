"""The real-brain acquisitions' source: a job's reconstruction read back as a volume to simulate
from, its brain found in its own intensities."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from model_export.experiments.real_brain_acquisitions import source_volumes
from service.io.volume import Volume, write_volume


def test_a_source_volume_is_simulated_from_with_its_own_brain(tmp_path: Path) -> None:
    """A reconstruction written as NIfTI comes back as a volume to simulate from: its voxels and
    placement as written, its brain the bright region (not the speck apart), centred where it lies."""
    image = np.zeros((40, 40, 40), np.float32)
    image[10:30, 12:32, 8:28] = 200.0
    image[1, 1, 1] = 200.0
    affine = np.diag([0.8, 0.8, 0.8, 1.0])
    affine[:3, 3] = [-16.0, -16.0, -16.0]
    write_volume(Volume(image, affine), tmp_path / "recon.nii.gz")
    (vol,) = source_volumes([tmp_path / "recon.nii.gz"])
    assert vol.name == "recon" and np.allclose(vol.affine, affine, atol=1e-4)
    assert np.allclose(vol.image, image) and vol.mask[1, 1, 1] == 0 and vol.mask[20, 22, 18] == 1
    assert np.allclose(vol.centre, (np.array([19.5, 21.5, 17.5]) * 0.8 - 16.0), atol=0.5)
