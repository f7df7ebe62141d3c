"""What a job keeps of its uploads for the worker: the decoded voxels and their placement, with the
transforms of a NIfTI header (how other readers place the stack), and nothing of a DICOM header."""

from __future__ import annotations

from pathlib import Path

import nibabel as nib
import numpy as np

from service.io.nifti_header import qform_from_sform
from service.io.readers import read_upload
from service.jobs.job_inputs import keep_volume, load_volume


def test_a_kept_nifti_stack_keeps_both_of_its_headers_transforms(tmp_path: Path) -> None:
    """A stack whose qform lies 15 mm from its sform comes back from the job's folder with the header's
    transforms (the move between its two readings) as well as its voxels and placement."""
    affine = np.diag([1.1, 0.9, 3.3, 1.0])
    image = nib.Nifti1Image(np.arange(60, dtype=np.float32).reshape(3, 4, 5), affine)
    image.set_sform(affine, 2)
    moved = affine.copy()
    moved[0, 3] = 15.0
    image.set_qform(moved, 1)
    nib.save(image, tmp_path / "s.nii.gz")
    upload = read_upload(tmp_path / "s.nii.gz", "s.nii.gz")
    keep_volume(upload, tmp_path / "stack0.npz")
    back = load_volume(tmp_path / "stack0.npz")
    assert back.nifti == upload.nifti and back.nifti is not None
    np.testing.assert_array_equal(back.array, upload.array)
    np.testing.assert_allclose(back.affine, affine, atol=1e-5)
    np.testing.assert_allclose(qform_from_sform(back.nifti)[:3, 3], [15.0, 0.0, 0.0], atol=1e-4)


def test_a_stack_of_another_format_or_an_earlier_job_has_no_header_transforms(tmp_path: Path) -> None:
    """A volume read from no NIfTI file keeps none; a folder written before they were kept reads as one."""
    from service.io.volume import Volume

    keep_volume(Volume(np.zeros((2, 3, 4), np.float32), np.eye(4)), tmp_path / "stack0.npz")
    assert load_volume(tmp_path / "stack0.npz").nifti is None
    with np.load(tmp_path / "stack0.npz") as kept:
        older = {k: kept[k] for k in kept.files if k != "nifti"}
    np.savez(tmp_path / "stack1.npz", **older)
    assert load_volume(tmp_path / "stack1.npz").nifti is None
