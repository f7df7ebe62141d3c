"""Readers recognise content, not names; DICOM (mosaic, multi-frame, zipped series) geometry."""

from __future__ import annotations

import gzip
import multiprocessing
import re
import zipfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from service.core.errors import UnsupportedFile, UnusableImage
from service.geometry import frames, se3
from service.io.limits import DecodeBudget
from service.io.readers import read_upload, sniff, validate
from service.io.volume import Volume, write_volume
from tests.conftest import SHARED_DATA

DICOM_DIR = SHARED_DATA / "dicom"


def oblique() -> np.ndarray:
    a = np.eye(4)
    a[:3, :3] = se3.so3_exp(np.array([0.2, -0.1, 0.3])) * [0.8, 0.8, 3.0]
    a[:3, 3] = [10.0, -20.0, 5.0]
    return a


@pytest.mark.parametrize(("suffix", "kind"), [(".nii.gz", "nifti-gz"), (".nii", "nifti"), (".nrrd", "nrrd"), (".mha", "mha")])
def test_formats_are_recognised_by_content_whatever_the_name(tmp_path: Path, suffix: str, kind: str) -> None:
    arr = np.random.default_rng(0).random((6, 7, 5)).astype(np.float32)
    path = tmp_path / f"v{suffix}"
    write_volume(Volume(arr, oblique()), path)
    renamed = tmp_path / "upload.bin"
    path.rename(renamed)
    assert sniff(renamed) == kind
    vol = read_upload(renamed, "upload.bin")
    np.testing.assert_allclose(vol.affine, oblique(), atol=1e-4)
    np.testing.assert_array_equal(vol.array, arr)
    assert renamed.exists()  # the upload is not moved away


def test_unknown_content_is_415(tmp_path: Path) -> None:
    p = tmp_path / "x.nii.gz"
    p.write_bytes(b"\x00" * 600)
    with pytest.raises(UnsupportedFile, match="x.nii.gz"):
        read_upload(p, "x.nii.gz")


def _write_series(folder: Path, vol: Volume, series_uid: str, times: list[str] | None = None) -> list[Path]:
    """One DICOM file per slice, written by SimpleITK's GDCM writer in a child process: the writer
    calls ``setlocale`` (leaving the C locale behind), which is not thread-safe, and the test process
    has other threads (servers, job runners) that must never see the locale change under them."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_write_series_files, folder, vol, series_uid, times).result()


def _write_series_files(folder: Path, vol: Volume, series_uid: str, times: list[str] | None) -> list[Path]:
    image = sitk.Cast(sitk.GetImageFromArray(vol.array.transpose(2, 1, 0).astype(np.int16)), sitk.sitkInt16)
    origin, spacing, direction = frames.itk_from_affine(vol.affine)
    image.SetOrigin(tuple(origin))
    image.SetSpacing(tuple(spacing))
    image.SetDirection(tuple(direction.ravel()))
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    paths = []
    for k in range(image.GetDepth()):
        sl = image[:, :, k]
        for tag, value in [("0008|0060", "MR"), ("0020|000e", series_uid), ("0020|000d", "1.2.826.0.1.3680043.2.1125.1"),
                           ("0020|0013", str(k + 1)), ("0010|0010", "Doe^Jane"),
                           ("0020|0032", "\\".join(map(str, image.TransformIndexToPhysicalPoint((0, 0, k))))),
                           ("0020|0037", "\\".join(map(str, direction[:, 0].tolist() + direction[:, 1].tolist()))),
                           ("0018|0050", str(spacing[2])), ("0028|0030", f"{spacing[1]}\\{spacing[0]}")]:
            sl.SetMetaData(tag, value)
        if times is not None:
            sl.SetMetaData("0008|0032", times[k])                # AcquisitionTime
        p = folder / f"{series_uid[-3:]}_{k:03d}.dcm"
        writer.SetFileName(str(p))
        writer.Execute(sl)
        paths.append(p)
    return paths


def test_zipped_dicom_series_keeps_geometry(tmp_path: Path) -> None:
    arr = (np.random.default_rng(1).random((12, 10, 6)) * 1000).astype(np.float32).round()
    aff = np.eye(4)
    aff[:3, :3] = se3.so3_exp(np.array([0.0, 0.0, 0.3])) * [0.9, 0.9, 3.0]
    aff[:3, 3] = [5.0, 6.0, -7.0]
    files = _write_series(tmp_path, Volume(arr, aff), "1.2.826.0.1.3680043.2.1125.101")
    z = tmp_path / "series.zip"
    with zipfile.ZipFile(z, "w") as f:
        for p in files:
            f.write(p, f"nested/dir/{p.name}")
    vol = read_upload(z, "series.zip")
    np.testing.assert_allclose(vol.affine, aff, atol=1e-3)
    np.testing.assert_allclose(vol.array, arr, atol=0.5)
    assert vol.slice_thickness_mm == pytest.approx(3.0)            # each file's SliceThickness


@pytest.mark.parametrize(("damage", "words"), [
    ("a file missing", "not evenly spaced (6 mm between slices 2 and 3, where the others lie 3 mm apart"),
    ("a file twice", "two of its files lie at one position"),
    ("no position", "ImagePositionPatient is missing in 1 of its 6 files"),
    ("one turned", "ImageOrientationPatient differ"),
    ("no orientation", "ImageOrientationPatient is missing or not two unit vectors"),
    ("pixel spacing 0", "PixelSpacing is missing or not positive in 6 of its 6 files"),
    ("sheared", "its files are shifted within their plane from one to the next (a drift of 5 mm over the stack)"),
])
def test_a_zipped_series_that_is_no_one_stack_is_422_not_a_made_up_grid(tmp_path: Path, damage: str, words: str) -> None:
    """GDCM stacks such files anyway, inventing a slice spacing or an orientation."""
    import pydicom

    arr = (np.random.default_rng(3).random((10, 10, 6)) * 1000).astype(np.float32).round()
    files = _write_series(tmp_path, Volume(arr, np.diag([1.0, 1.0, 3.0, 1.0])), "1.2.3.555")
    sets = [pydicom.dcmread(p) for p in files]
    if damage == "a file missing":
        sets.pop(2)
    elif damage == "a file twice":
        sets[3].ImagePositionPatient = sets[2].ImagePositionPatient
    elif damage == "no position":
        del sets[4].ImagePositionPatient
    elif damage == "one turned":
        sets[1].ImageOrientationPatient = [1, 0, 0, 0, 0, 1]
    elif damage == "no orientation":
        for d in sets:
            d.ImageOrientationPatient = [0, 0, 0, 0, 0, 0]
    elif damage == "sheared":                                  # each file 1 mm further along its rows
        for k, d in enumerate(sets):
            d.ImagePositionPatient = [float(d.ImagePositionPatient[0]) + k, *d.ImagePositionPatient[1:]]
    else:
        for d in sets:
            d.PixelSpacing = [0, 0]
    z = tmp_path / "series.zip"
    with zipfile.ZipFile(z, "w") as f:
        for k, d in enumerate(sets):
            d.save_as(tmp_path / f"m{k}.dcm")
            f.write(tmp_path / f"m{k}.dcm", f"m{k}.dcm")
    with pytest.raises(UnusableImage, match=f"series.zip: a DICOM series of {len(sets)} files, but .*{re.escape(words)}"):
        read_upload(z, "series.zip")


@pytest.mark.parametrize(("times", "order"), [
    (["101500.50", "101502.70", "101500.94", "101503.14", "101501.38", "101503.58"], (0, 2, 4, 1, 3, 5)),
    (["101500"] * 6, None),                                   # the series' start on every slice: no order
    (["235959.0", "", "000001.0", "000002", "000003", "000004"], None),   # a slice without a time
])
def test_a_zipped_series_keeps_the_order_of_its_acquisition_times(tmp_path: Path, times: list[str],
                                                                   order: tuple | None) -> None:
    arr = (np.random.default_rng(2).random((10, 10, 6)) * 1000).astype(np.float32).round()
    files = _write_series(tmp_path, Volume(arr, np.diag([1.0, 1.0, 3.0, 1.0])), "1.2.3.444", times)
    z = tmp_path / "series.zip"
    with zipfile.ZipFile(z, "w") as f:
        for p in reversed(files):                             # members out of order: sorted by position
            f.write(p, p.name)
    vol = read_upload(z, "series.zip")
    np.testing.assert_allclose(vol.array, arr, atol=0.5)
    assert vol.acquisition_order == order


def _zip_of(path: Path, files: list[Path]) -> Path:
    with zipfile.ZipFile(path, "w") as f:
        for p in files:
            f.write(p, p.name)
    return path


def test_zip_with_two_series_or_none(tmp_path: Path) -> None:
    arr = np.ones((8, 8, 3), np.float32)
    files = _write_series(tmp_path, Volume(arr, np.diag([1.0, 1, 2, 1])), "1.2.3.111")
    files += _write_series(tmp_path, Volume(arr, np.diag([1.0, 1, 2, 1])), "1.2.3.222")
    with pytest.raises(UnusableImage, match="2 DICOM series"):
        read_upload(_zip_of(tmp_path / "two.zip", files), "two.zip")
    z2 = tmp_path / "none.zip"
    with zipfile.ZipFile(z2, "w") as f:
        f.writestr("readme.txt", "hello")
    with pytest.raises(UnsupportedFile, match="no DICOM series"):
        read_upload(z2, "none.zip")


def test_siemens_mosaic_is_demosaiced() -> None:
    path = DICOM_DIR / "dicom3tools_0051_siemens_pasl_mosaic.dcm"
    if not path.exists():
        pytest.skip(f"needs the shared DICOM examples at {DICOM_DIR}")
    vol = read_upload(path, path.name)
    assert vol.array.shape == (72, 72, 20)
    np.testing.assert_allclose(vol.spacing, [3.0, 3.0, 6.0], atol=1e-6)
    # Tiles hold different slices: neighbouring slices correlate, but are not identical.
    a, b = vol.array[:, :, 9].ravel(), vol.array[:, :, 10].ravel()
    assert 0.3 < np.corrcoef(a, b)[0, 1] < 0.9999
    # The slice normal is the cross product of the DICOM row and column directions (LPS -> RAS).
    assert abs(np.linalg.det(vol.affine[:3, :3] / vol.spacing)) == pytest.approx(1.0)
    # nibabel's reader, written independently, puts every voxel where this one does (its arrays are
    # [row, column, slice], its world LPS).
    import pydicom
    from nibabel.nicom import dicomwrappers
    theirs = dicomwrappers.wrapper_from_data(pydicom.dcmread(path))
    np.testing.assert_array_equal(theirs.get_data(), vol.array.transpose(1, 0, 2))
    np.testing.assert_allclose(np.diag([-1.0, -1.0, 1.0, 1.0]) @ theirs.affine, vol.affine[:, [1, 0, 2, 3]], atol=1e-6)


def test_an_enhanced_multiframe_without_geometry_is_422_not_a_made_up_grid() -> None:
    """pydicom's sample holds pixels only: no position, orientation or pixel spacing anywhere."""
    path = DICOM_DIR / "pydicom_data_emri_small_enhancedMR_10frames.dcm"
    if not path.exists():
        pytest.skip(f"needs the shared DICOM examples at {DICOM_DIR}")
    with pytest.raises(UnusableImage, match="without ImagePositionPatient, ImageOrientationPatient, PixelSpacing"):
        read_upload(path, path.name)


@pytest.mark.parametrize("compressed", [False, True])
def test_impossible_nifti_headers_are_refused_not_read_as_something_else(tmp_path: Path, compressed: bool) -> None:
    """A data offset inside the header (or not a number, or past the data), a bitpix that is not the
    datatype's with the data cut to what the bitpix would need: 415 naming the file. ITK reads each
    without a word (every voxel shifted by the header's last bytes; the missing voxels zero-filled),
    and an offset under 352 also hid a NaN from the scan for them."""
    path = tmp_path / "v.nii"
    data = np.random.default_rng(1).random((6, 7, 5)).astype(np.float32)
    data[2, 3, 1] = np.nan
    write_volume(Volume(data, oblique()), path)
    good = path.read_bytes()
    cases = []
    for offset in (np.nan, 1e9, -5.0, 0.0, 348.0):
        raw = bytearray(good)
        raw[108:112] = np.float32(offset).tobytes()
        cases.append((bytes(raw), "NIfTI"))
    raw = bytearray(good[:352 + data.size])                      # float32 data cut to a quarter ...
    raw[72:74] = np.int16(8).tobytes()                           # ... which a bitpix of 8 would fit
    cases.append((bytes(raw), "bitpix 8 for datatype 16"))
    for content, words in cases:
        target = tmp_path / ("odd.nii.gz" if compressed else "odd.nii")
        target.write_bytes(gzip.compress(content) if compressed else content)
        with pytest.raises(UnsupportedFile) as info:
            read_upload(target, "odd.nii")
        assert "odd.nii" in info.value.detail and words in info.value.detail, info.value.detail
    path.write_bytes(good)
    with pytest.raises(UnusableImage, match="NaN"):              # the same file as written: its NaN found
        read_upload(path, "v.nii")


@pytest.mark.parametrize(("pixdim", "codes", "words"), [
    ((0.0, 0.0, 0.0), (1, 0), "its NIfTI header gives no voxel size"),
    ((np.nan, 1.0, 1.0), (1, 0), "its NIfTI header gives no voxel size"),
    # neither transform: ITK, nibabel and the standard place the voxels three ways (mirror images)
    ((1.0, 1.0, 3.0), (0, 0), "its NIfTI header places its voxels nowhere"),
    ((1.0, -1.0, 3.0), (1, 0), "its NIfTI header gives no voxel size"),
    ((0.0, 0.0, 0.0), (1, 1), "its NIfTI sform gives an axis no length")])    # the sform places the voxels
def test_a_nifti_header_without_voxel_sizes_is_422_not_1_mm(tmp_path: Path, pixdim: tuple, codes: tuple,
                                                            words: str) -> None:
    """ITK puts 1 mm where a header's pixdim is 0, negative or NaN, whatever its q/s-form codes say."""
    path = tmp_path / "v.nii"
    write_volume(Volume(np.random.default_rng(1).random((6, 7, 5)).astype(np.float32), oblique()), path)
    raw = bytearray(path.read_bytes())
    raw[80:92] = np.asarray(pixdim, "<f4").tobytes()
    raw[252:256] = np.asarray(codes, "<i2").tobytes()
    if codes[1]:
        raw[280:328] = np.zeros(12, "<f4").tobytes()                      # an s-form of zeros
    path.write_bytes(bytes(raw))
    with pytest.raises(UnusableImage, match=rf"mine\.nii: {words}"):
        read_upload(path, "mine.nii")


@pytest.mark.parametrize(("spacing", "words"), [((30.0, 30.0, 3.0), "voxel size 30, 30, 3 mm"),
                                                ((0.01, 1.0, 3.0), "voxel size 0.01, 1, 3 mm: under 0.05 mm"),
                                                ((5.0, 5.0, 3.0), "field of view 1000 x 1005 x 15 mm")])
def test_a_grid_no_mri_acquisition_has_is_422_before_any_stage_sizes_arrays_by_it(
        tmp_path: Path, spacing: tuple, words: str) -> None:
    path = tmp_path / "v.nii.gz"
    write_volume(Volume(np.ones((200, 201, 5), np.float32), np.diag([*spacing, 1.0])), path)
    with pytest.raises(UnusableImage, match=f"mine.nii.gz: {words}"):
        read_upload(path, "mine.nii.gz")
    write_volume(Volume(np.ones((200, 201, 5), np.float32), np.diag([1.0, 1.0, 3.0, 1.0])), path)
    assert read_upload(path, "mine.nii.gz").array.shape == (200, 201, 5)


@pytest.mark.parametrize("damage", ["orientation with 5 values", "no orientation", "empty shared groups"])
def test_dicom_with_broken_geometry_is_refused(tmp_path: Path, damage: str) -> None:
    pydicom = pytest.importorskip("pydicom")
    name = ("pydicom_data_emri_small_enhancedMR_10frames.dcm" if damage == "empty shared groups"
            else "dicom3tools_0051_siemens_pasl_mosaic.dcm")
    if not (DICOM_DIR / name).exists():
        pytest.skip(f"needs the shared DICOM examples at {DICOM_DIR}")
    ds = pydicom.dcmread(DICOM_DIR / name)
    if damage == "orientation with 5 values":
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1]
    elif damage == "no orientation":
        del ds.ImageOrientationPatient
    else:
        ds.SharedFunctionalGroupsSequence = pydicom.Sequence([])
    path = tmp_path / "broken.dcm"
    ds.save_as(path)
    # a mosaic's orientation is checked as a classic file's (422, naming the tag); the enhanced file's
    # frames have no geometry at all (415)
    expected = UnsupportedFile if damage == "empty shared groups" else UnusableImage
    with pytest.raises(expected, match="broken.dcm" + ("" if expected is UnsupportedFile else ": ImageOrientationPatient")):
        read_upload(path, "broken.dcm")


def test_an_enhanced_multiframe_keeps_the_order_of_its_frame_times(tmp_path: Path) -> None:
    """Frames stored out of spatial order, each with its position and acquisition time: the reader
    sorts them along the normal and keeps the order in which those positions were acquired."""
    pydicom = pytest.importorskip("pydicom")
    src = DICOM_DIR / "pydicom_data_emri_small_enhancedMR_10frames.dcm"
    if not src.exists():
        pytest.skip(f"needs the shared DICOM examples at {DICOM_DIR}")
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    ds = pydicom.dcmread(src)
    stored_depth = [3, 0, 7, 1, 9, 4, 2, 8, 5, 6]            # frame f lies at depth stored_depth[f]
    acquired_at = [2, 7, 4, 9, 5, 0, 8, 1, 3, 6]              # frame f was acquired acquired_at[f]-th
    frames_ = []
    for f in range(10):
        item = Dataset()
        pos, content = Dataset(), Dataset()
        pos.ImagePositionPatient = [0.0, 0.0, 4.0 * stored_depth[f]]
        content.FrameAcquisitionDateTime = f"20261124101500.{acquired_at[f]:02d}"
        item.PlanePositionSequence = Sequence([pos])
        item.FrameContentSequence = Sequence([content])
        frames_.append(item)
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames_)
    ds.ImageOrientationPatient, ds.PixelSpacing = [1, 0, 0, 0, 1, 0], [1.0, 1.0]
    path = tmp_path / "enhanced.dcm"
    ds.save_as(path)
    vol = read_upload(path, "enhanced.dcm")
    np.testing.assert_allclose(vol.spacing[2], 4.0)
    depth_of_time = {acquired_at[f]: stored_depth[f] for f in range(10)}
    assert vol.acquisition_order == tuple(depth_of_time[t] for t in range(10))
    np.testing.assert_allclose(vol.array[:, :, 0], ds.pixel_array[1].T)      # depth 0 is frame 1


def test_a_series_of_slices_closer_than_its_pixels_is_422_not_cut_along_a_pixel_axis(tmp_path: Path) -> None:
    """3 mm slices every 1.0 mm with 1.2 mm pixels: the axis of largest spacing would be an in-plane one."""
    arr = (np.random.default_rng(8).random((10, 10, 12)) * 1000).astype(np.float32).round()
    files = _write_series(tmp_path, Volume(arr, np.diag([1.2, 1.2, 1.0, 1.0])), "1.2.3.777")
    with pytest.raises(UnusableImage, match="overlap.zip: its slices lie 1 mm apart, closer than its 1.2 mm pixels"):
        read_upload(_zip_of(tmp_path / "overlap.zip", files), "overlap.zip")


@pytest.mark.parametrize("suffix", [".nii.gz", ".nrrd"])
def test_a_stack_file_of_slices_closer_than_its_pixels_is_422_not_cut_along_a_pixel_axis(tmp_path: Path,
                                                                                        suffix: str) -> None:
    """A NIfTI or NRRD stack of 1.5 mm pixels with slices 1.2 mm apart (overlapping): its file does not
    say which axis is the slices', and the axis of largest spacing would be an in-plane one. Slices
    as far apart as the pixels are a stack as before."""
    arr = (np.random.default_rng(9).random((30, 30, 40)) * 1000).astype(np.float32).round()
    for spacing in ([1.5, 1.5, 1.2], [1.125, 1.125, 1.1]):             # overlapping; nearly cubic voxels
        write_volume(Volume(arr, np.diag([*spacing, 1.0])), path := tmp_path / f"overlap{suffix}")
        with pytest.raises(UnusableImage, match=f"overlap{suffix}: its first two voxel axes share the largest"):
            read_upload(path, path.name)
    for spacing in ([1.5, 1.5, 1.5], [1.2, 1.5, 1.5], [1.0, 1.0, 0.9999]):   # the third axis the slices' (a tie
        write_volume(Volume(arr, np.diag([*spacing, 1.0])), ok := tmp_path / f"ok{suffix}")  # holds it, or none)
        assert read_upload(ok, ok.name).array.shape == (30, 30, 40)
    # A DICOM series says its slice axis: pixels of 1.0 x 1.2 mm, slices 1.2 mm apart are a stack.
    files = _write_series(tmp_path, Volume(arr[:, :, :6], np.diag([1.0, 1.2, 1.2, 1.0])), "1.2.3.778")
    assert read_upload(_zip_of(tmp_path / "series.zip", files), "series.zip").array.shape == (30, 30, 6)


def test_a_zipped_series_is_unpacked_into_the_scratch_folder_given(tmp_path: Path, monkeypatch) -> None:
    """The service passes the request's or job's own folder: a process killed mid-read leaves the
    decoded DICOM files (every tag of them) where that request's or job's clean-up removes them."""
    import service.io.archive as archive

    arr = (np.random.default_rng(9).random((8, 8, 4)) * 1000).astype(np.float32).round()
    z = _zip_of(tmp_path / "s.zip", _write_series(tmp_path, Volume(arr, np.diag([1.0, 1.0, 3.0, 1.0])), "1.2.3.888"))
    seen: list[Path] = []
    monkeypatch.setattr(archive.sitk.ImageSeriesReader, "GetGDCMSeriesFileNames",
                        lambda self, folder, uid: seen.append(Path(folder)) or sorted(
                            str(p) for p in Path(folder).rglob("*") if p.is_file()))
    scratch = tmp_path / "job" / "inputs"
    scratch.mkdir(parents=True)
    read_upload(z, "s.zip", scratch=scratch)
    assert len(seen) == 1 and seen[0].parent == scratch and seen[0].name.startswith("svrnet-zip-")
    assert list(scratch.iterdir()) == []                     # removed again once read


@pytest.mark.parametrize("codes", [(1, 2), (1, 0), (0, 0)])
def test_a_nifti2_file_is_read_as_its_nifti1_twin(tmp_path: Path, codes: tuple[int, int]) -> None:
    """NIfTI-2 (which SimpleITK does not read) gives the voxels and placement of the same image as NIfTI-1,
    by the sform where its code says so, else by the qform, and is refused as it is without either;
    gzipped or not; scaled voxels alike."""
    import nibabel
    arr = (np.random.default_rng(8).random((9, 8, 6)) * 500).astype(np.int16)
    voxel = oblique()
    sform = voxel.copy()
    sform[:3, 3] += [4.0, -3.0, 2.0]                                  # sform and qform disagree by a shift
    read = {}
    for kind, image_class in (("1", nibabel.Nifti1Image), ("2", nibabel.Nifti2Image)):
        image = image_class(arr, None)
        image.set_qform(voxel, code=codes[0])
        image.set_sform(sform, code=codes[1])
        image.header.set_zooms((0.8, 0.8, 3.0))                       # the voxel sizes the qform and pixdim say
        image.header.set_slope_inter(0.5, 10.0)
        for suffix in (".nii", ".nii.gz"):
            path = tmp_path / f"v{kind}{suffix}"
            nibabel.save(image, path)
            if codes == (0, 0):
                with pytest.raises(UnusableImage, match=rf"{path.name}: its NIfTI header places its voxels nowhere"):
                    read_upload(path, path.name)
                continue
            read[kind + suffix] = read_upload(path, path.name)
    for vol in read.values():
        np.testing.assert_allclose(vol.array, arr.astype(np.float32) * 0.5 + 10.0, rtol=1e-6)
        np.testing.assert_allclose(vol.affine, read["1.nii"].affine, atol=1e-4)
    if codes != (0, 0):
        np.testing.assert_allclose(read["2.nii"].affine, sform if codes[1] > 0 else voxel, atol=1e-4)
    else:
        assert not read


def test_a_nifti2_file_of_several_volumes_complex_truncated_or_too_large_is_refused(tmp_path: Path) -> None:
    import gzip

    import nibabel

    from service.core.errors import PayloadTooLarge
    nibabel.save(nibabel.Nifti2Image(np.ones((9, 8, 6), np.complex64), np.diag([1.0, 1.0, 3.0, 1.0])), tmp_path / "c.nii")
    with pytest.raises(UnusableImage, match="unsupported pixel type complex64"):
        read_upload(tmp_path / "c.nii", "c.nii")
    huge = nibabel.Nifti2Image(np.ones((4, 4, 4), np.float32), np.eye(4))
    huge.header.set_data_shape((4000, 4000, 4000))                     # declares 256 GB
    nibabel.save(nibabel.Nifti2Image(np.ones((4, 4, 4), np.float32), np.eye(4)), tmp_path / "small.nii")
    raw = bytearray((tmp_path / "small.nii").read_bytes())
    raw[:540] = huge.header.binaryblock
    (tmp_path / "huge.nii.gz").write_bytes(gzip.compress(bytes(raw) + bytes(1 << 20)))
    budget = DecodeBudget(1 << 22).file("huge.nii.gz")
    with pytest.raises(PayloadTooLarge):
        read_upload(tmp_path / "huge.nii.gz", "huge.nii.gz", budget=budget)
    assert budget.inflated == 0                                         # refused from its header, nothing inflated
    inside = bytearray((tmp_path / "small.nii").read_bytes())
    inside[168:176] = (0).to_bytes(8, "little")                         # vox_offset 0: the header read as voxels
    (tmp_path / "inside.nii").write_bytes(bytes(inside))
    with pytest.raises(UnsupportedFile, match="vox_offset < 544"):
        read_upload(tmp_path / "inside.nii", "inside.nii")
    arr = np.ones((9, 8, 6, 2), np.float32)
    nibabel.save(nibabel.Nifti2Image(arr, np.diag([1.0, 1.0, 3.0, 1.0])), tmp_path / "v4.nii")
    with pytest.raises(UnusableImage, match="2 volumes"):
        read_upload(tmp_path / "v4.nii", "v4.nii")
    nibabel.save(nibabel.Nifti2Image(arr[..., 0], np.diag([1.0, 1.0, 3.0, 1.0])), tmp_path / "v.nii")
    data = (tmp_path / "v.nii").read_bytes()
    (tmp_path / "cut.nii").write_bytes(data[: len(data) - 100])
    with pytest.raises(UnsupportedFile, match="cut.nii"):
        read_upload(tmp_path / "cut.nii", "cut.nii")


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz", ".mha"])
def test_finite_voxels_beyond_float32s_range_are_422_not_read_as_infinite(tmp_path: Path, suffix: str) -> None:
    """A float64 file's 1e300 would become inf where the service computes in float32: refused as NaN and
    inf are, not read as a stack whose slices then hold no brain."""
    array = np.ones((6, 20, 20))
    array[3, 10, 10] = 1e300
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((1.0, 1.0, 3.0))
    path = tmp_path / f"big{suffix}"
    sitk.WriteImage(image, str(path))
    with pytest.raises(UnusableImage) as info:
        read_upload(path, path.name)
    assert path.name in info.value.detail and "float32" in info.value.detail


@pytest.mark.parametrize("stored", ["offset int16", "z-score float32", "positive offset uint16"])
def test_a_file_stored_with_an_offset_is_read_as_its_magnitudes(tmp_path: Path, stored: str) -> None:
    """A magnitude image stored with values below zero (a signed export's offset, a z-score) or with its
    air lifted above zero (a positive offset: its lowest value a floor, held by 1 % of the values or more) is read
    with its background at 0, as the scanner's own file would be: the same values (a z-score up to
    its scale), where before its brain sat on a negative floor that the localiser's percentile
    scaling and N4's multiplicative model cannot take."""
    rng = np.random.default_rng(3)
    magnitudes = np.zeros((6, 40, 40), np.float32)
    magnitudes[:, 10:30, 12:28] = rng.uniform(100, 900, (6, 20, 16)).round()
    if stored == "offset int16":
        array, scale = (magnitudes - 1024).astype(np.int16), 1.0
    elif stored == "positive offset uint16":             # the air lifted to 1000 (a rescale intercept)
        array, scale = (magnitudes + 1000).astype(np.uint16), 1.0
    else:
        scale = float(magnitudes.std())
        array = ((magnitudes - magnitudes.mean()) / scale).astype(np.float32)
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((1.0, 1.0, 3.0))
    path = tmp_path / "stack.nii.gz"
    sitk.WriteImage(image, str(path))
    read = read_upload(path, path.name).array.transpose(2, 1, 0)
    assert read.min() == 0.0
    np.testing.assert_allclose(read * scale, magnitudes, atol=1e-3 * magnitudes.max())


@pytest.mark.parametrize("fill", [-1024, -32768])
def test_a_tools_fill_value_is_no_background(tmp_path: Path, fill: int) -> None:
    """A resampled stack whose corners a tool padded with a fill value (3.5 % of its voxels): the fill
    reads as 0 and the rest as it was (the fill was taken for the background and lifted the image by
    it: at -32768 no brain was found). An offset export whose air sits exactly on its lowest value
    keeps its background there (the test above)."""
    rng = np.random.default_rng(5)
    magnitudes = rng.uniform(0, 20, (6, 40, 40)).round().astype(np.float32)           # air, with its noise
    magnitudes[:, 10:30, 12:28] = rng.uniform(100, 900, (6, 20, 16)).round()
    corners = np.zeros((40, 40), bool)
    corners[:5, :5] = corners[:5, -5:] = corners[-5:, :5] = corners[-5:, -5:] = True    # 100 of 1600 px
    corners &= np.add.outer(np.arange(40), np.arange(40)) % 2 == 0               # half: 3.1 %
    array = np.where(corners[None], np.float32(fill), magnitudes).astype(np.int16)
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((1.0, 1.0, 3.0))
    path = tmp_path / "stack.nii.gz"
    sitk.WriteImage(image, str(path))
    read = read_upload(path, path.name).array.transpose(2, 1, 0)
    np.testing.assert_array_equal(read, np.where(corners[None], 0.0, magnitudes))


def test_a_file_without_negative_values_is_read_as_it_is(tmp_path: Path) -> None:
    """Values above zero without a floor (a noise floor, no value held by 1 % of the voxels) are kept."""
    array = np.random.default_rng(4).uniform(5, 50, (6, 20, 20)).astype(np.float32)
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((1.0, 1.0, 3.0))
    sitk.WriteImage(image, str(tmp_path / "s.nii"))
    np.testing.assert_array_equal(read_upload(tmp_path / "s.nii", "s.nii").array.transpose(2, 1, 0), array)


def test_an_oblique_series_whose_positions_are_written_to_a_tenth_of_a_mm_is_one_stack(tmp_path: Path) -> None:
    """Some exports and anonymisers write ImagePositionPatient with one decimal: an oblique stack's
    slices then scatter within their plane by up to 0.087 mm about their line, more than 5 % of a
    1.1 mm pixel, which the reader took for a sheared grid (422). Rounding does not accumulate, a
    shear does: the series is read as one stack, its affine within the rounding of the truth."""
    import pydicom

    from service.io.acquisition_geometry import SPACING_TOLERANCE

    arr = (np.random.default_rng(5).random((10, 10, 24)) * 1000).astype(np.float32).round()
    aff = np.eye(4)
    aff[:3, :3] = se3.so3_exp(np.array([0.12, -0.08, 0.3])) * [1.1, 1.1, 3.3]
    aff[:3, 3] = [12.34, -56.78, 9.87]
    sets = [pydicom.dcmread(p) for p in _write_series(tmp_path, Volume(arr, aff), "1.2.3.556")]
    for d in sets:
        d.ImagePositionPatient = [round(float(v), 1) for v in d.ImagePositionPatient]
    positions = np.array([[float(v) for v in d.ImagePositionPatient] for d in sets])
    normal = aff[:3, 2] / np.linalg.norm(aff[:3, 2])
    offsets = positions - np.outer(positions @ normal, normal)
    assert np.linalg.norm(offsets - offsets[0], axis=1).max() > SPACING_TOLERANCE * 1.1     # what was refused
    z = tmp_path / "rounded.zip"
    with zipfile.ZipFile(z, "w") as f:
        for k, d in enumerate(sets):
            d.save_as(tmp_path / f"r{k}.dcm")
            f.write(tmp_path / f"r{k}.dcm", f"r{k}.dcm")
    vol = read_upload(z, "rounded.zip")
    assert vol.array.shape == arr.shape
    np.testing.assert_allclose(vol.affine, aff, atol=0.1)


def test_a_voxel_of_absurd_size_is_named_so_not_a_shear() -> None:
    """A header whose voxel edge is 1e300 mm makes the axes' angle meaningless: the answer names the
    voxel size, as it does for a voxel of 30 mm."""
    for edge in (30.0, 1e300):
        with pytest.raises(UnusableImage, match="voxel size .* beyond (20 mm|any size)"):
            validate(Volume(np.ones((4, 4, 3), np.float32), np.diag([edge, 1.0, 3.0, 1.0])), "big.nii")
