"""Single DICOM files: Siemens mosaics cut into their declared tiles, Enhanced multi-frame files placed
frame by frame; any file whose frames make no one stack is refused, never given a made-up grid."""

from __future__ import annotations

import re
import struct
import zipfile
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset, FileDataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import EnhancedMRImageStorage, ExplicitVRLittleEndian, MRImageStorage, generate_uid

from service.core.errors import UnusableImage
from service.geometry import frames
from service.io.readers import read_upload


def _dataset(path: Path, sop_class: str, pixels: np.ndarray) -> FileDataset:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = sop_class, generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = sop_class, meta.MediaStorageSOPInstanceUID, "MR"
    ds.Rows, ds.Columns = pixels.shape[-2:]
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.PixelData = np.ascontiguousarray(pixels, np.uint16).tobytes()
    return ds


def numbered(k: int, shape: tuple[int, int]) -> np.ndarray:
    """A frame that holds its number: ``100 (k + 1)``, but for one pixel of air (0) in its last corner, so
    that a reader keeps its values as they are (a floor above zero would be moved to 0)."""
    frame = np.full(shape, 100 * (k + 1), np.uint16)
    frame[-1, -1] = 0
    return frame


def _csa_header(tags: dict[str, list[float]]) -> bytes:
    """A Siemens CSA2 header (``SV10``) holding ``tags`` as decimal strings, as the scanner writes them."""
    out = b"SV10" + b"\x04\x03\x02\x01" + struct.pack("<2I", len(tags), 77)
    for name, values in tags.items():
        out += struct.pack("<64si4s3i", name.encode(), len(values), b"FD", 3, len(values), 77)
        for value in values:
            data = f"{value:.8f}".encode() + b"\0"
            out += struct.pack("<4i", len(data), len(data), 77, len(data)) + data + b"\0" * (-len(data) % 4)
    return out


def _mosaic_file(path: Path, slices: np.ndarray, n_declared: int, acquisition_matrix: list[int] | None,
                 csa: bytes | None = None, pixel_spacing: tuple[float, float] = (2.0, 2.0)) -> Path:
    """A Siemens mosaic of ``slices`` ``[n, rows, cols]`` (ceil(sqrt(n)) tiles a side, empty tiles after
    the last), declaring ``n_declared`` images; ``csa``: its CSA image header (0029,1010);
    ``pixel_spacing``: PixelSpacing (between rows, between columns)."""
    n, tr, tc = slices.shape
    side = int(np.ceil(np.sqrt(n)))
    mosaic = np.zeros((side * tr, side * tc), np.uint16)
    for k in range(n):
        mosaic[(k // side) * tr:(k // side + 1) * tr, (k % side) * tc:(k % side + 1) * tc] = slices[k]
    ds = _dataset(path, MRImageStorage, mosaic)
    ds.ImageType = ["ORIGINAL", "PRIMARY", "M", "MOSAIC"]
    ds.PixelSpacing, ds.SliceThickness, ds.SpacingBetweenSlices = list(pixel_spacing), 3.0, 3.5
    ds.ImageOrientationPatient, ds.ImagePositionPatient = [1, 0, 0, 0, 1, 0], [-100.0, -80.0, 10.0]
    if acquisition_matrix is not None:
        ds.AcquisitionMatrix = acquisition_matrix
    ds.add_new((0x0019, 0x0010), "LO", "SIEMENS MR HEADER")
    ds.add_new((0x0019, 0x100A), "US", n_declared)
    if csa is not None:
        ds.add_new((0x0029, 0x0010), "LO", "SIEMENS CSA HEADER")
        ds.add_new((0x0029, 0x1010), "OB", csa)
    pydicom.dcmwrite(str(path), ds, enforce_file_format=True)
    return path


def test_a_mosaic_is_cut_into_its_declared_tiles(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    slices = (rng.random((10, 24, 20)) * 1000 + 100).astype(np.uint16)     # 4 x 4 tiles, 6 empty
    vol = read_upload(_mosaic_file(tmp_path / "m.dcm", slices, 10, [20, 0, 0, 18]), "m.dcm")
    assert vol.array.shape == (20, 24, 10)                                  # [column, row, slice]
    np.testing.assert_array_equal(vol.array.transpose(2, 1, 0), slices.astype(np.float32))
    np.testing.assert_allclose(vol.spacing, [2.0, 2.0, 3.5])
    assert vol.slice_thickness_mm == 3.0
    # Siemens writes the position of a virtual image the mosaic's size, centred where each tile is:
    # the first tile's centre lies where the mosaic's centre does (LPS (-100, -80, 10), 96 x 80 of 2 mm).
    centre_lps = np.array([-100.0, -80.0, 10.0]) + [(80 - 1) / 2 * 2.0, (96 - 1) / 2 * 2.0, 0.0]
    tile_centre = vol.affine @ [(20 - 1) / 2, (24 - 1) / 2, 0.0, 1.0]
    np.testing.assert_allclose(tile_centre[:3], centre_lps * [-1, -1, 1], atol=1e-9)


def test_a_mosaic_of_oblong_pixels_takes_each_spacing_along_its_own_axis(tmp_path: Path) -> None:
    """PixelSpacing is (between rows, between columns): 2.0 mm down a column, 1.5 mm along a row. The
    columns (i) are 1.5 mm apart, the rows (j) 2.0 mm, and the first tile's centre lies at the
    mosaic's centre, each half-width measured in its own pixels (a swap moves it by 8 mm)."""
    slices = (np.random.default_rng(7).random((10, 24, 20)) * 1000 + 100).astype(np.uint16)
    vol = read_upload(_mosaic_file(tmp_path / "m.dcm", slices, 10, None, pixel_spacing=(2.0, 1.5)), "m.dcm")
    np.testing.assert_allclose(vol.spacing, [1.5, 2.0, 3.5])
    centre_lps = np.array([-100.0, -80.0, 10.0]) + [(80 - 1) / 2 * 1.5, (96 - 1) / 2 * 2.0, 0.0]
    tile_centre = vol.affine @ [(20 - 1) / 2, (24 - 1) / 2, 0.0, 1.0]
    np.testing.assert_allclose(tile_centre[:3], centre_lps * [-1, -1, 1], atol=1e-9)


@pytest.mark.parametrize(("tag", "value", "needle"), [
    ("PixelSpacing", [-2.0, 2.0], "PixelSpacing is missing or not positive"),          # read as a mirrored image
    ("ImageOrientationPatient", [2, 0, 0, 0, 2, 0], "not two unit vectors"),          # read as 2 mm voxels
    ("ImageOrientationPatient", [1, 0, 0, 0.5, 0.866, 0], "not two unit vectors at right angles"),
])
def test_a_mosaic_s_geometry_is_checked_as_a_classic_file_s(tmp_path: Path, tag: str, value: list,
                                                            needle: str) -> None:
    """A mosaic's PixelSpacing and ImageOrientationPatient pass the checks a classic file's do: a
    negative spacing (a mirrored stack) or orientation vectors that are not unit and at right angles
    are refused, not read into a wrong geometry."""
    import pydicom

    slices = (np.random.default_rng(6).random((10, 24, 20)) * 1000 + 100).astype(np.uint16)
    path = _mosaic_file(tmp_path / "m.dcm", slices, 10, None)
    ds = pydicom.dcmread(str(path))
    setattr(ds, tag, value)
    ds.save_as(str(path))
    with pytest.raises(UnusableImage, match=needle):
        read_upload(path, "m.dcm")


@pytest.mark.parametrize(("declared", "matrix", "needle"), [
    (2, None, "beyond its NumberOfImagesInMosaic 2"),          # 2 x 2 tiles of 48 x 40: images after the 2nd
    (9, None, "does not fit a mosaic of 96 x 80"),             # 3 x 3 tiles: 80 / 3 pixels
    (12, None, "tile 10 of the mosaic's 12 images"),           # the right layout, two empty tiles counted
    (10, [40, 0, 0, 40], "smaller than the acquired matrix"),  # tiles of 24 x 20 for a 40 x 40 acquisition
])
def test_a_mosaic_whose_count_disagrees_with_its_tiles_is_refused(tmp_path: Path, declared: int,
                                                                  matrix: list[int] | None, needle: str) -> None:
    """Ten images of 24 x 20 in 4 x 4 tiles, declared otherwise: refused, never cut across tiles."""
    slices = (np.random.default_rng(5).random((10, 24, 20)) * 1000 + 100).astype(np.uint16)
    with pytest.raises(UnusableImage, match=needle):
        read_upload(_mosaic_file(tmp_path / "m.dcm", slices, declared, matrix), "m.dcm")


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_a_mosaic_s_tiles_follow_its_csa_slice_normal(tmp_path: Path, direction: float) -> None:
    """Tile k of a mosaic lies k slice spacings from the first tile along the CSA SliceNormalVector: the
    image's normal (LPS +z here) for ascending slices, its opposite for descending ones. Each tile holds
    its own number, so every slice the reader returns is checked against where its tile was acquired."""
    n = 5
    slices = np.stack([numbered(k, (24, 20)) for k in range(n)])
    csa = _csa_header({"SliceNormalVector": [0.0, 0.0, direction], "NumberOfImagesInMosaic": [float(n)]})
    vol = read_upload(_mosaic_file(tmp_path / "m.dcm", slices, n, None, csa), "m.dcm")
    first_tile = np.array([-100.0, -80.0, 10.0]) + [(60 - 20) / 2 * 2.0, (72 - 24) / 2 * 2.0, 0.0]     # LPS
    for s in range(n):
        k = int(vol.array[0, 0, s]) // 100 - 1                     # the tile this slice came from
        acquired_lps = first_tile + k * 3.5 * np.array([0.0, 0.0, direction])
        np.testing.assert_allclose((vol.affine @ [0, 0, s, 1])[:3], acquired_lps * [-1, -1, 1], atol=1e-9)
    without = read_upload(_mosaic_file(tmp_path / "plain.dcm", slices, n, None), "plain.dcm")
    assert np.allclose(without.affine, vol.affine) == (direction > 0)   # no CSA header: taken as ascending
    negative = _mosaic_file(tmp_path / "neg.dcm", slices, n, None, csa)
    ds = pydicom.dcmread(negative)
    ds.SpacingBetweenSlices = -3.5                                  # the CSA normal says which way, not the sign
    pydicom.dcmwrite(str(negative), ds, enforce_file_format=True)
    np.testing.assert_allclose(read_upload(negative, "neg.dcm").affine, vol.affine, atol=1e-9)


def test_a_mosaic_keeps_the_order_its_csa_times_give(tmp_path: Path) -> None:
    """An interleaved mosaic: the CSA MosaicRefAcqTimes (ms within the repetition) give the acquisition order."""
    slices = (np.random.default_rng(7).random((5, 24, 20)) * 1000 + 100).astype(np.uint16)
    times = {"MosaicRefAcqTimes": [0.0, 1000.0, 250.0, 1250.0, 500.0]}
    vol = read_upload(_mosaic_file(tmp_path / "m.dcm", slices, 5, None, _csa_header(times)), "m.dcm")
    assert vol.acquisition_order == (0, 2, 4, 1, 3)
    short = {"MosaicRefAcqTimes": [0.0, 1000.0]}                       # not every tile's: no order
    assert read_upload(_mosaic_file(tmp_path / "s.dcm", slices, 5, None, _csa_header(short)), "s.dcm").acquisition_order is None


def _csa_text(name: str, text: str) -> bytes:
    """A CSA2 header whose one tag holds ``text`` as a string (VR ST)."""
    data = text.encode() + b"\0"
    return (b"SV10" + b"\x04\x03\x02\x01" + struct.pack("<2I", 1, 77)
            + struct.pack("<64si4s3i", name.encode(), 3, b"ST", 3, 3, 77)
            + b"".join(struct.pack("<4i", len(data), len(data), 77, len(data)) + data + b"\0" * (-len(data) % 4)
                       for _ in range(3)))


@pytest.mark.parametrize(("csa", "needle"), [
    (_csa_header({"SliceNormalVector": [1.0, 0.0, 0.0]}), "does not lie along the normal"),
    (_csa_text("SliceNormalVector", "up"), "cannot be read"),
    (b"SV10\x04\x03\x02\x01" + struct.pack("<2I", 1, 77) + b"\0" * 20, "cannot be read"),
])
def test_a_mosaic_whose_csa_header_contradicts_or_is_broken_is_refused(tmp_path: Path, csa: bytes, needle: str) -> None:
    slices = (np.random.default_rng(6).random((4, 24, 20)) * 1000 + 100).astype(np.uint16)
    with pytest.raises(UnusableImage, match=needle):
        read_upload(_mosaic_file(tmp_path / "m.dcm", slices, 4, None, csa), "m.dcm")


ROW, COL = np.array([0.8, 0.6, 0.0]), np.array([0.0, 0.0, -1.0])      # an oblique, LPS
NORMAL = np.cross(ROW, COL)


def _enhanced_file(path: Path, frames_: np.ndarray, positions: list, orientations: list | None = None,
                   spacing: list | None = (1.2, 0.9), shared_orientation: list | None = None) -> Path:
    """An Enhanced MR file of ``frames_`` ``[n, rows, cols]``: each frame's ImagePositionPatient (None: none),
    orientation (per frame, or shared) and pixel measures (shared; None: none)."""
    ds = _dataset(path, EnhancedMRImageStorage, frames_)
    ds.NumberOfFrames = len(frames_)
    shared = Dataset()
    if spacing is not None:
        measures = Dataset()
        measures.PixelSpacing, measures.SliceThickness = list(spacing), 3.0
        shared.PixelMeasuresSequence = Sequence([measures])
    if shared_orientation is not None:
        orient = Dataset()
        orient.ImageOrientationPatient = list(shared_orientation)
        shared.PlaneOrientationSequence = Sequence([orient])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    items = []
    for f, position in enumerate(positions):
        item = Dataset()
        if position is not None:
            pos = Dataset()
            pos.ImagePositionPatient = [float(x) for x in position]
            item.PlanePositionSequence = Sequence([pos])
        if orientations is not None:
            orient = Dataset()
            orient.ImageOrientationPatient = list(orientations[f])
            item.PlaneOrientationSequence = Sequence([orient])
        items.append(item)
    ds.PerFrameFunctionalGroupsSequence = Sequence(items)
    pydicom.dcmwrite(str(path), ds, enforce_file_format=True)
    return path


def _frames(n: int = 8) -> np.ndarray:
    return (np.random.default_rng(6).random((n, 12, 10)) * 1000 + 100).astype(np.uint16)


def test_an_enhanced_multiframe_is_placed_frame_by_frame_and_ordered_along_its_normal(tmp_path: Path) -> None:
    stored_depth = [3, 0, 7, 5, 1, 6, 2, 4]
    origin = np.array([-40.0, 20.0, 35.0])
    positions = [origin + 3.3 * d * NORMAL for d in stored_depth]
    pixels = _frames()
    vol = read_upload(_enhanced_file(tmp_path / "e.dcm", pixels, positions,
                                     shared_orientation=[*ROW, *COL]), "e.dcm")
    lps = np.eye(4)
    lps[:3, 0], lps[:3, 1], lps[:3, 2], lps[:3, 3] = ROW * 0.9, COL * 1.2, NORMAL * 3.3, origin
    np.testing.assert_allclose(vol.affine, frames.ras_affine_from_lps(lps), atol=1e-6)
    for f, d in enumerate(stored_depth):                   # depth d holds frame f, its columns along i
        np.testing.assert_array_equal(vol.array[:, :, d], pixels[f].T.astype(np.float32))
    assert vol.slice_thickness_mm == 3.0                   # as stated (PixelMeasuresSequence), not the 3.3 mm spacing


@pytest.mark.parametrize("spacing", [3.3, -3.3])
def test_a_legacy_multiframe_stacks_its_frames_by_the_sign_of_its_spacing(tmp_path: Path, spacing: float) -> None:
    """A multi-frame MR image without functional groups: frame k lies k x SpacingBetweenSlices along
    the normal of its ImageOrientationPatient from its ImagePositionPatient, against the normal where
    the spacing is negative (frames stored downwards). Each frame holds its own number, so every
    slice the reader returns is checked against where its frame was acquired."""
    n, origin = 6, np.array([-40.0, 20.0, 35.0])
    ds = _dataset(tmp_path / "legacy.dcm", MRImageStorage, np.stack([numbered(k, (12, 10)) for k in range(n)]))
    ds.NumberOfFrames = n
    ds.ImageOrientationPatient, ds.ImagePositionPatient = [*ROW, *COL], list(origin)
    ds.PixelSpacing, ds.SliceThickness, ds.SpacingBetweenSlices = [1.2, 0.9], 3.0, spacing
    pydicom.dcmwrite(str(tmp_path / "legacy.dcm"), ds, enforce_file_format=True)
    vol = read_upload(tmp_path / "legacy.dcm", "legacy.dcm")
    np.testing.assert_allclose(vol.spacing, [0.9, 1.2, 3.3])
    for s in range(n):
        k = int(vol.array[0, 0, s]) // 100 - 1                     # the frame this slice came from
        acquired_lps = origin + k * spacing * NORMAL
        np.testing.assert_allclose((vol.affine @ [0, 0, s, 1])[:3], acquired_lps * [-1, -1, 1], atol=1e-6)


def test_frames_without_positions_take_the_spacing_their_functional_group_states(tmp_path: Path) -> None:
    """Enhanced MR states SpacingBetweenSlices in its Pixel Measures functional group: frames placed by
    one position lie that far apart, not at the file's top-level SliceThickness."""
    n, origin = 5, np.array([-40.0, 20.0, 35.0])
    ds = _dataset(tmp_path / "grouped.dcm", MRImageStorage, np.stack([numbered(k, (12, 10)) for k in range(n)]))
    ds.NumberOfFrames = n
    ds.ImageOrientationPatient, ds.ImagePositionPatient = [*ROW, *COL], list(origin)
    ds.SliceThickness = 3.0
    measures = Dataset()
    measures.PixelSpacing, measures.SpacingBetweenSlices = [1.2, 0.9], 3.3
    shared = Dataset()
    shared.PixelMeasuresSequence = Sequence([measures])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    pydicom.dcmwrite(str(tmp_path / "grouped.dcm"), ds, enforce_file_format=True)
    vol = read_upload(tmp_path / "grouped.dcm", "grouped.dcm")
    np.testing.assert_allclose(vol.spacing, [0.9, 1.2, 3.3])
    for s in range(n):
        k = int(vol.array[0, 0, s]) // 100 - 1
        np.testing.assert_allclose((vol.affine @ [0, 0, s, 1])[:3], (origin + 3.3 * k * NORMAL) * [-1, -1, 1], atol=1e-6)


@pytest.mark.parametrize("where", ["per frame", "shared"])
def test_an_enhanced_multiframe_s_rescale_is_each_frame_s_own(tmp_path: Path, where: str) -> None:
    """Enhanced MR keeps RescaleSlope and RescaleIntercept in the Pixel Value Transformation functional
    group (PS3.3 C.7.6.16.2.9), per frame (as Philips writes them) or shared; each frame is rescaled by
    its own, as nibabel does (stored 100 everywhere)."""
    n = 4
    stored = np.full((n, 12, 10), 100, np.uint16)
    stored[:, -1, -1] = 0                          # air: the values are read as they are
    path = _enhanced_file(tmp_path / "e.dcm", stored,
                          [np.array([-40.0, 20.0, 35.0]) + 3.3 * d * NORMAL for d in range(n)],
                          shared_orientation=[*ROW, *COL])
    ds = pydicom.dcmread(path)
    slopes, intercepts = ([1.0, 2.0, 0.5, 4.0], [0.0, 10.0, -5.0, 0.0]) if where == "per frame" else ([3.0] * n, [-200.0] * n)
    for f in range(n) if where == "per frame" else [None]:
        transform = Dataset()
        transform.RescaleSlope, transform.RescaleIntercept, transform.RescaleType = slopes[f or 0], intercepts[f or 0], "US"
        target = ds.SharedFunctionalGroupsSequence[0] if f is None else ds.PerFrameFunctionalGroupsSequence[f]
        target.PixelValueTransformationSequence = Sequence([transform])
    ds.save_as(path)
    vol = read_upload(path, "e.dcm")
    np.testing.assert_allclose(vol.array[3, 5, :], [100 * a + b for a, b in zip(slopes, intercepts)])


def _damaged(kind: str) -> dict:
    origin = np.array([-40.0, 20.0, 35.0])
    positions = [origin + 3.3 * d * NORMAL for d in range(8)]
    out = {"positions": positions, "shared_orientation": [*ROW, *COL]}
    if kind == "a frame missing":
        out["positions"] = positions[:3] + [None] + positions[4:]
    elif kind == "uneven":
        out["positions"] = [p + (3.3 * NORMAL if d >= 4 else 0) for d, p in enumerate(positions)]
    elif kind == "repeated":
        out["positions"] = positions[:4] * 2
    elif kind == "two orientations":
        out["orientations"] = [[*ROW, *COL]] * 4 + [[1, 0, 0, 0, 1, 0]] * 4
        out["shared_orientation"] = None
    elif kind == "sheared":
        out["positions"] = [p + d * 1.0 * ROW for d, p in enumerate(positions)]
    elif kind == "no orientation":
        out["shared_orientation"] = None
    elif kind == "no pixel measures":
        out["spacing"] = None
    return out


@pytest.mark.parametrize(("kind", "words"), [
    ("a frame missing", "ImagePositionPatient is missing in 1 of its 8 frames"),
    ("uneven", "its slices are not evenly spaced (6.6 mm between slices 4 and 5, where the others lie 3.3 mm apart"),
    ("repeated", "two of its frames lie at one position"),
    ("two orientations", "its frames' ImageOrientationPatient differ"),
    ("sheared", "its frames are shifted within their plane"),
    ("no orientation", "ImageOrientationPatient is missing or not two unit vectors"),
    ("no pixel measures", "PixelSpacing is missing or not positive in 8 of its 8 frames"),
])
def test_an_enhanced_multiframe_whose_frames_make_no_one_stack_is_422(tmp_path: Path, kind: str, words: str) -> None:
    path = _enhanced_file(tmp_path / "e.dcm", _frames(), **_damaged(kind))
    with pytest.raises(UnusableImage, match=f"e.dcm: a multi-frame DICOM of 8 frames, but {re.escape(words)}"):
        read_upload(path, "e.dcm")


def test_a_colour_dicom_is_422_not_its_channels_taken_for_slices(tmp_path: Path) -> None:
    """An RGB image (SamplesPerPixel 3) decodes to rows x cols x 3: never read as rows slices of 3 pixels."""
    from pydicom import uid

    from tests.support import corpus

    ds = corpus._dataset(40, 48, 1)
    ds.SamplesPerPixel, ds.PhotometricInterpretation, ds.PlanarConfiguration = 3, "RGB", 0
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 8, 8, 7
    ds.PixelData = np.random.default_rng(0).integers(0, 255, (40, 48, 3), np.uint8).tobytes()
    path = tmp_path / "rgb.dcm"
    path.write_bytes(corpus._file(ds, uid.ExplicitVRLittleEndian))
    with pytest.raises(UnusableImage, match="rgb.dcm: DICOM pixel data with 3 samples per pixel"):
        read_upload(path, "rgb.dcm")


def test_pixel_data_padded_by_less_than_a_frame_is_read_and_a_frame_more_refused(tmp_path: Path) -> None:
    """Trailing padding shorter than a frame (pydicom drops it) is no extra frame: read as declared."""
    from service.core.errors import UnsupportedFile
    from tests.support import corpus

    pixels = (np.arange(3 * 8 * 6) % 500).astype(np.uint16).reshape(3, 8, 6)
    for extra, refused in ((6, False), (8 * 6 * 2, True)):
        ds = corpus._dataset(8, 6, 3)
        ds.PixelData = pixels.tobytes() + b"\0" * extra
        path = tmp_path / f"pad{extra}.dcm"
        path.write_bytes(corpus._file(ds, ExplicitVRLittleEndian))
        if refused:
            with pytest.raises(UnsupportedFile, match="longer than its header declares"):
                read_upload(path, path.name)
        else:
            assert read_upload(path, path.name).array.shape == (6, 8, 3)


@pytest.mark.parametrize(("photometric", "named"), [("PALETTE COLOR", "PALETTE COLOR"), ("DOE^JANE^X", "other than")])
def test_a_photometric_interpretation_is_named_only_when_it_is_a_defined_term(tmp_path: Path, photometric: str,
                                                                            named: str) -> None:
    """The tag's defined terms are named; free text (a name could be stuffed there) never comes back."""
    path = tmp_path / "frames.dcm"
    ds = _dataset(path, MRImageStorage, np.ones((4, 8, 8), np.uint16))
    ds.NumberOfFrames = 4
    ds.PhotometricInterpretation = photometric
    ds.save_as(str(path), enforce_file_format=True)
    with pytest.raises(UnusableImage) as info:
        read_upload(path, "frames.dcm")
    assert named in info.value.detail and "DOE" not in info.value.detail, info.value.detail


def test_a_zipped_series_places_each_pixel_by_its_file_and_keeps_each_file_s_rescale(tmp_path: Path) -> None:
    """A classic series zipped, oblique, with pixels 1.2 mm between rows and 0.8 mm between columns,
    its files stored from the top of the stack down and each with its own RescaleSlope and
    RescaleIntercept: every voxel lies at its pixel's centre by the standard (PS3.3 C.7.6.2.1.1: IPP +
    column x spacing along the row + row x spacing along the column) and holds its file's value (the
    series reader would take the first file's integer type and round the others')."""
    rows, cols, n, between = 12, 10, 6, 3.3
    slopes, intercepts = [0.01, 0.01, 2.5, 0.5, 0.01, 1.0], [0.0, 5.0, -3.0, 0.0, 1.5, 0.0]   # the bottom file: 1, 0
    top = np.array([-30.0, 12.0, 40.0])
    uids = [generate_uid() for _ in range(3)]
    stored = [(np.arange(rows * cols).reshape(rows, cols) + 1000 * f + 1).astype(np.uint16) for f in range(n)]
    with zipfile.ZipFile(tmp_path / "s.zip", "w") as archive:
        for f in range(n):
            ds = _dataset(tmp_path / f"{f}.dcm", MRImageStorage, stored[f])
            ds.SeriesInstanceUID, ds.StudyInstanceUID, ds.FrameOfReferenceUID = uids
            ds.InstanceNumber, ds.ImagePositionPatient = f + 1, [float(x) for x in top - f * between * NORMAL]
            ds.ImageOrientationPatient, ds.PixelSpacing, ds.SliceThickness = [*ROW, *COL], [1.2, 0.8], 3.0
            ds.RescaleSlope, ds.RescaleIntercept = slopes[f], intercepts[f]
            pydicom.dcmwrite(str(tmp_path / f"{f}.dcm"), ds, enforce_file_format=True)
            archive.write(tmp_path / f"{f}.dcm", f"{f}.dcm")
    vol = read_upload(tmp_path / "s.zip", "s.zip")
    lps = frames.LPS_FROM_RAS @ vol.affine
    for f, r, c in ((0, 0, 0), (2, 11, 3), (5, 4, 9), (3, 7, 7), (1, 3, 2), (4, 10, 1)):
        point = top - f * between * NORMAL + c * 0.8 * ROW + r * 1.2 * COL
        index = np.linalg.solve(lps, [*point, 1.0])[:3]
        assert np.allclose(index, np.round(index), atol=1e-4), index
        i, j, k = (int(v) for v in np.round(index))
        assert vol.array[i, j, k] == pytest.approx(stored[f][r, c] * slopes[f] + intercepts[f], rel=1e-5)


def test_a_zip_s_member_names_never_choose_where_its_files_are_written(tmp_path: Path) -> None:
    """A valid series whose members are named to escape the scratch folder (an absolute path, and a
    chain of ``..`` that lands in the same folder from any depth of the system's temporary folder): the
    series is read whole, and nothing is written where the names point."""
    from tests.support import corpus

    target = tmp_path / "outside"
    target.mkdir()
    climb = "../" * 40 + target.relative_to(target.anchor).as_posix()
    pixels = [numbered(k, (8, 6)) for k in range(3)]
    names = [f"{target.as_posix()}/abs.dcm", f"{climb}/rel.dcm", f"..\\..\\{target.name}\\win.dcm"]
    (tmp_path / "series.zip").write_bytes(corpus.zipped({name: corpus.dicom(p, k) for k, (name, p)
                                                         in enumerate(zip(names, pixels))}))
    vol = read_upload(tmp_path / "series.zip", "series.zip")
    assert vol.array.shape[2] == 3 and sorted(np.unique(vol.array).tolist()) == [0.0, 100.0, 200.0, 300.0]
    assert list(target.iterdir()) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["outside", "series.zip"]
