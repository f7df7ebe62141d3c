"""NIfTI files are placed as the standard (and nibabel, FSL) place them: by the sform whenever its code
is above 0, with its own voxel sizes; a sheared sform is refused; masks carry the upload's transforms."""

from __future__ import annotations

from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.errors import UnusableImage
from service.io.nifti_header import NiftiTransforms, copy_transforms, parse, qform_affine, read_transforms
from service.io.readers import read_upload
from service.io.volume import Volume, read_volume, write_volume

SHAPE = (12, 10, 8)


def sform_of(spacing: tuple[float, float, float], degrees: float, origin: tuple[float, float, float]) -> np.ndarray:
    a = np.eye(4)
    a[:3, :3] = Rotation.from_euler("zx", [degrees, degrees / 2], degrees=True).as_matrix() * spacing
    a[:3, 3] = origin
    return a


def write(path: Path, sform: np.ndarray | None, sform_code: int, qform: np.ndarray | None, qform_code: int,
          pixdim: tuple[float, float, float] | None = None) -> Path:
    """A NIfTI-1 file whose header fields are exactly these (nibabel would otherwise keep them in step)."""
    data = np.arange(np.prod(SHAPE), dtype=np.float32).reshape(SHAPE)
    img = nib.Nifti1Image(data, None)
    header = img.header
    if qform is not None:
        header.set_qform(qform, code=qform_code)
    else:
        header["qform_code"] = 0
    if sform is not None:
        header.set_sform(sform, code=sform_code)
    else:
        header["sform_code"] = 0
    if pixdim is not None:
        header["pixdim"][1:4] = pixdim
    nib.save(img, str(path))
    return path


def test_an_sform_only_file_is_placed_by_the_sform_not_by_pixdim(tmp_path: Path) -> None:
    sform = sform_of((1.1, 0.9, 3.3), 25, (-40, 12, 7))
    for pixdim in ((1.0, 1.0, 1.0), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0)):
        path = write(tmp_path / "s.nii", sform, 1, None, 0, pixdim)
        vol = read_upload(path, "s.nii")
        np.testing.assert_allclose(vol.affine, sform, atol=1e-5)
        np.testing.assert_allclose(vol.affine, nib.load(str(path)).affine, atol=1e-5)    # as nibabel, FSL
        np.testing.assert_allclose(vol.spacing, [1.1, 0.9, 3.3], atol=1e-5)


@pytest.mark.parametrize("sform_code", [1, 2, 3, 4])
def test_the_sform_wins_over_a_disagreeing_qform_whatever_its_code(tmp_path: Path, sform_code: int) -> None:
    sform = sform_of((1.1, 0.9, 3.3), 30, (-40, 12, 7))
    qform = sform_of((1.1, 0.9, 3.3), 0, (-28, 12, 7))
    vol = read_upload(write(tmp_path / "sq.nii", sform, sform_code, qform, 1), "sq.nii")
    np.testing.assert_allclose(vol.affine, sform, atol=1e-5)
    assert vol.nifti is not None and (vol.nifti.sform_code, vol.nifti.qform_code) == (sform_code, 1)


def test_without_an_sform_the_qform_places_the_voxels(tmp_path: Path) -> None:
    qform = sform_of((1.1, 0.9, 3.3), 40, (-28, 12, 7))
    qform[:3, 0] *= -1                                        # left-handed: qfac -1
    path = write(tmp_path / "q.nii.gz", None, 0, qform, 1)
    np.testing.assert_allclose(read_upload(path, "q.nii.gz").affine, qform, atol=1e-4)


@pytest.mark.parametrize("units", [1, 3, 0, 10])                       # metres, microns, unknown, mm and s
def test_the_qform_places_the_voxels_in_millimetres_as_the_sform_does_whatever_the_unit(tmp_path: Path,
                                                                                         units: int) -> None:
    """A header's ``xyzt_units`` changes neither transform (as nibabel and FSL read them): the same
    qform-only header is placed where its sform-only twin and its NIfTI-2 twin are, never a thousand
    times larger or smaller (ITK scales the qform alone by the unit)."""
    qform = sform_of((1.1, 0.9, 3.3), 40, (-28, 12, 7))
    placed = []
    for name, sform_code, qform_code, image_class in (("q.nii", 0, 1, nib.Nifti1Image), ("s.nii", 1, 0, nib.Nifti1Image),
                                                      ("q2.nii", 0, 1, nib.Nifti2Image)):
        img = image_class(np.arange(np.prod(SHAPE), dtype=np.float32).reshape(SHAPE) + 1, None)
        img.header.set_qform(qform, code=qform_code)
        img.header.set_sform(qform, code=sform_code)
        img.header["xyzt_units"] = units
        nib.save(img, str(tmp_path / name))
        placed.append(read_upload(tmp_path / name, name).affine)
    for affine in placed:
        np.testing.assert_allclose(affine, qform, atol=1e-4)
    np.testing.assert_allclose(placed[0], nib.load(str(tmp_path / "q.nii")).affine, atol=1e-5)


def test_a_sheared_sform_is_refused_naming_the_shear(tmp_path: Path) -> None:
    sform = sform_of((1.1, 0.9, 3.3), 0, (0, 0, 0))
    sform[0, 1] = 0.2                                          # the second axis leans on the first
    for qform in (None, sform_of((1.1, 0.9, 3.3), 0, (0, 0, 0))):
        path = write(tmp_path / "shear.nii", sform, 1, qform, 0 if qform is None else 1)
        with pytest.raises(UnusableImage, match="shear.nii: its NIfTI sform is sheared"):
            read_upload(path, "shear.nii")


def test_copied_transforms_make_a_written_file_read_as_the_upload(tmp_path: Path) -> None:
    sform = sform_of((1.1, 0.9, 3.3), 30, (-40, 12, 7))
    qform = sform_of((1.1, 0.9, 3.3), 0, (-28, 12, 7))
    upload = read_upload(write(tmp_path / "sq.nii", sform, 2, qform, 1), "sq.nii")
    out = tmp_path / "mask.nii.gz"
    write_volume(Volume(np.ones(SHAPE, np.uint8), upload.affine), out)
    copy_transforms(out, upload.nifti)
    written, source = nib.load(str(out)).header, nib.load(str(tmp_path / "sq.nii")).header
    for get in ("get_best_affine", "get_qform", "get_sform"):
        np.testing.assert_allclose(getattr(written, get)(), getattr(source, get)(), atol=1e-5)
    assert (int(written["sform_code"]), int(written["qform_code"])) == (2, 1)
    assert parse(b"not a header" * 50) is None and read_transforms(tmp_path / "sq.nii") == upload.nifti
    np.testing.assert_allclose(read_volume(out).affine, sform, atol=1e-5)         # the service's own reader too


def test_qform_affine_is_nibabels_for_any_rotation_qfac_and_voxel_size() -> None:
    """Against nibabel's own reading of the same header fields, over random rotations (a turn by 180
    degrees among them, whose ``a`` is 0), both ``qfac`` signs and random voxel edges and offsets."""
    rng = np.random.default_rng(7)
    rotations = list(Rotation.random(40, random_state=rng).as_matrix()) + [np.diag([1.0, -1.0, -1.0])]
    for rotation in rotations:
        qfac = rng.choice([-1.0, 1.0])
        edges = rng.uniform(0.3, 5.0, 3)
        affine = np.eye(4)
        affine[:3, :3] = rotation * edges * np.array([1.0, 1.0, qfac])
        affine[:3, 3] = rng.uniform(-200, 200, 3)
        header = nib.Nifti1Header()
        header.set_qform(affine, code=1)
        fields = NiftiTransforms(1, 0, tuple(float(x) for x in header["pixdim"][:4]),
                                 tuple(float(header[k]) for k in ("quatern_b", "quatern_c", "quatern_d",
                                                                  "qoffset_x", "qoffset_y", "qoffset_z")), (0.0,) * 12)
        np.testing.assert_allclose(qform_affine(fields), header.get_qform(), atol=1e-5)
        np.testing.assert_allclose(qform_affine(fields), affine, atol=1e-4)        # the simulated truth


@pytest.mark.parametrize("cos", [3e-4, 9e-4])
def test_an_sform_a_hair_off_right_angles_is_read_as_it_is(tmp_path: Path, cos: float) -> None:
    """An sform-only file whose axes lie within the service's shear tolerance (1e-3) but beyond
    ITK's (which refuses it as not orthonormal) is read, voxels and sform as they are, not refused
    as an unreadable file."""
    sform = sform_of((1.1, 0.9, 3.3), 25, (-40, 12, 7))
    sform[:3, 1] += cos * 0.9 * sform[:3, 0] / 1.1            # the second axis leans towards the first
    path = write(tmp_path / "h.nii.gz", sform, 1, None, 0)
    vol = read_upload(path, "h.nii.gz")
    np.testing.assert_allclose(vol.affine, sform, atol=1e-5)
    np.testing.assert_array_equal(vol.array, np.asarray(nib.load(str(path)).dataobj))


@pytest.mark.parametrize(("units", "named"), [(1, "metres"), (3, "micrometres")])
def test_a_grid_refused_in_a_header_that_names_another_unit_says_so(tmp_path: Path, units: int, named: str) -> None:
    """Distances written in metres (0.0011 "mm" pixels) are refused as no MRI grid, and the answer
    names the header's unit, which the service (as nibabel and FSL) does not apply."""
    sform = sform_of((0.0011, 0.0009, 0.0033), 25, (-0.04, 0.012, 0.007))
    path = write(tmp_path / "u.nii", sform, 1, None, 0)
    raw = bytearray(path.read_bytes())
    raw[123] = units | 8                                      # its unit, and seconds
    path.write_bytes(bytes(raw))
    assert parse(bytes(raw[:348])).spatial_unit == units
    with pytest.raises(UnusableImage, match=f"its NIfTI header says its distances are in {named}"):
        read_upload(path, "u.nii")


@pytest.mark.parametrize("units", [1, 3, 2 | 8])
def test_a_written_mask_names_the_uploads_distance_unit_and_lies_on_it_in_itk(units: int, tmp_path: Path) -> None:
    """A stack whose header says metres (or microns) is placed by ITK a thousand times larger (or
    smaller) than it reads in millimetres: the mask written over it says the same unit, so that ITK
    puts mask and stack on one grid; the time unit the service writes is kept."""
    sitk = pytest.importorskip("SimpleITK")
    affine = sform_of((1.1, 0.9, 3.3), 30, (-40, 12, 7))
    img = nib.Nifti1Image(np.zeros(SHAPE, np.float32), affine)
    img.header.set_qform(affine, code=1)
    img.header.set_sform(affine, code=1)
    img.header["xyzt_units"] = units
    nib.save(img, str(tmp_path / "stack.nii"))
    upload = read_upload(tmp_path / "stack.nii", "stack.nii")
    out = tmp_path / "mask.nii.gz"
    write_volume(Volume(np.ones(SHAPE, np.uint8), upload.affine), out)
    written_time = int(nib.load(str(out)).header["xyzt_units"]) & ~7
    copy_transforms(out, upload.nifti)
    assert int(nib.load(str(out)).header["xyzt_units"]) == (units & 7) | written_time
    stack, mask = sitk.ReadImage(str(tmp_path / "stack.nii")), sitk.ReadImage(str(out))
    np.testing.assert_allclose(mask.GetSpacing(), stack.GetSpacing(), rtol=1e-5)
    np.testing.assert_allclose(mask.GetOrigin(), stack.GetOrigin(), rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(read_volume(out).affine, affine, atol=1e-4)       # the service reads it in mm
