"""MRD image geometry against a simulated truth: every pixel of every slice of an oblique stack lands
where the stack's RAS affine says, through the header's LPS fields, for even and odd matrices."""

from __future__ import annotations

import io

import ismrmrd
import numpy as np
import pytest

from service.core.errors import UnusableImage
from service.geometry import frames, se3
from service.io.volume import Volume
from service.mrd.images import (POSE_META_KEYS, SliceGeometry, check_image, image_from_slice, pixel_count,
                                pose_from_meta, slice_from_image, with_pose)

FLOAT32_EPS = float(np.finfo(np.float32).eps)


def oblique_stack(shape: tuple[int, int, int], seed: int, mirrored: bool = False) -> Volume:
    """A stack with an oblique RAS affine (anisotropic pixels, thick slices) off the isocentre;
    ``mirrored``: left-handed (the normal against read x phase, as many NIfTI stacks are)."""
    rng = np.random.default_rng(seed)
    affine = np.eye(4)
    affine[:3, :3] = se3.so3_exp(rng.normal(size=3)) * [0.9, 1.1, -3.5 if mirrored else 3.5]
    affine[:3, 3] = rng.uniform(-60, 60, 3)
    return Volume(rng.uniform(0, 1000, shape).astype(np.float32), affine)


def slice_affine(volume: Volume, k: int) -> np.ndarray:
    """Voxel ``(x, y, 0, 1)`` of slice ``k`` -> RAS: the stack's affine moved ``k`` slices along its normal."""
    a = volume.affine.copy()
    a[:3, 3] += k * a[:3, 2]
    return a


def pixel_grid(nx: int, ny: int) -> np.ndarray:
    """Homogeneous ``(x, y, 0, 1)`` of every pixel, ``[nx * ny, 4]``."""
    x, y = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size), np.ones(x.size)], axis=1)


def truth(volume: Volume, k: int) -> np.ndarray:
    """World RAS mm of every pixel of slice ``k``, straight from the stack's affine."""
    nx, ny = volume.array.shape[:2]
    ijk = pixel_grid(nx, ny)
    ijk[:, 2] = k
    return (volume.affine @ ijk.T).T[:, :3]


def wire(image: ismrmrd.Image) -> ismrmrd.Image:
    """The image after an MRD stream: serialised and read back by ismrmrd."""
    buffer = io.BytesIO()
    ismrmrd.ProtocolSerializer(buffer).serialize(image)
    buffer.seek(0)
    return next(ismrmrd.ProtocolDeserializer(buffer).deserialize())


SHAPES = [(7, 5, 4), (8, 6, 3), (8, 5, 3), (9, 10, 2)]   # odd/odd, even/even and mixed matrices


@pytest.mark.parametrize("mirrored", [False, True])
@pytest.mark.parametrize("shape", SHAPES)
def test_geometry_maps_every_pixel_where_the_stack_affine_does(shape: tuple[int, int, int], mirrored: bool) -> None:
    volume = oblique_stack(shape, seed=sum(shape), mirrored=mirrored)
    nx, ny, nz = shape
    for k in range(nz):
        geometry = SliceGeometry.of_slice((nx, ny), slice_affine(volume, k))
        world = (geometry.scanner_from_voxel() @ pixel_grid(nx, ny).T).T[:, :3]
        np.testing.assert_allclose(world, truth(volume, k), rtol=0, atol=1e-6)


@pytest.mark.parametrize("shape", SHAPES)
def test_header_fields_follow_the_mrd_definition(shape: tuple[int, int, int]) -> None:
    """Independently of the conversion code: position is the slice's centre in LPS, the directions are
    the LPS columns, the field of view is matrix x pixel size, and data[0, 0, y, x] is pixel (x, y)."""
    volume = oblique_stack(shape, seed=3)
    nx, ny, nz = shape
    lps = frames.LPS_FROM_RAS @ volume.affine
    spacing = np.linalg.norm(lps[:3, :3], axis=0)
    for k in range(nz):
        image = wire(image_from_slice(volume.array[:, :, k], slice_affine(volume, k), series=4, slice_index=k))
        centre = lps @ [nx / 2, ny / 2, k, 1.0]
        tolerance = 8 * FLOAT32_EPS * (1 + np.abs(centre).max())
        np.testing.assert_allclose(image.position, centre[:3], rtol=0, atol=tolerance)
        for field, column in (("read_dir", 0), ("phase_dir", 1), ("slice_dir", 2)):
            np.testing.assert_allclose(getattr(image, field), lps[:3, column] / spacing[column], atol=1e-6)
        np.testing.assert_allclose(image.field_of_view, [nx * spacing[0], ny * spacing[1], spacing[2]], rtol=1e-6)
        assert tuple(image.matrix_size) == (nx, ny, 1) and image.slice == k and image.image_series_index == 4
        x, y = nx - 1, 1
        assert image.data[0, 0, y, x] == volume.array[x, y, k]


def test_the_first_pixel_lies_where_gadgetron_puts_a_dicom_image_s_first_pixel() -> None:
    """A scanner's header, read independently of the conversion code: Gadgetron writes the DICOM
    ImagePositionPatient of an MRD image as ``position - field_of_view[0] / 2 * read_dir -
    field_of_view[1] / 2 * phase_dir`` (its DicomFinishGadget), the Fourier reconstruction's centre at
    pixel ``n / 2``; pixel (x, y) lies x and y pixels on from there. 256 x 224 pixels of 1.25 mm,
    oblique."""
    rng = np.random.default_rng(2)
    rotation = se3.so3_exp(rng.normal(0, 0.5, 3))
    header = ismrmrd.ImageHeader()
    header.matrix_size[:] = (256, 224, 1)
    header.field_of_view[:] = (320.0, 280.0, 3.0)
    header.position[:] = (-10.5, 22.25, 40.0)
    for field, column in (("read_dir", 0), ("phase_dir", 1), ("slice_dir", 2)):
        getattr(header, field)[:] = rotation[:, column]
    position, read, phase = (np.array(getattr(header, f), np.float64) for f in ("position", "read_dir", "phase_dir"))
    first = position - 160.0 * read - 140.0 * phase                                   # LPS
    ras = SliceGeometry.of_header(header).scanner_from_voxel()
    for x, y in ((0, 0), (255, 0), (17, 200)):
        want = first + 1.25 * x * read + 1.25 * y * phase
        np.testing.assert_allclose(frames.LPS_FROM_RAS @ ras @ [x, y, 0, 1.0], [*want, 1.0], atol=1e-4)


@pytest.mark.parametrize("shape", SHAPES)
def test_round_trip_through_an_mrd_stream(shape: tuple[int, int, int]) -> None:
    """Pixels come back exactly; positions to the precision of the header's float32 fields."""
    volume = oblique_stack(shape, seed=11)
    nx, ny, nz = shape
    for k in range(nz):
        pixels, scanner_from_voxel = slice_from_image(wire(image_from_slice(volume.array[:, :, k],
                                                                            slice_affine(volume, k))))
        np.testing.assert_array_equal(pixels, volume.array[:, :, k])
        expected = truth(volume, k)
        world = (scanner_from_voxel @ pixel_grid(nx, ny).T).T[:, :3]
        tolerance = 16 * FLOAT32_EPS * (1 + np.abs(expected).max() + nx + ny)
        np.testing.assert_allclose(world, expected, rtol=0, atol=tolerance)
        assert tolerance < 1e-3


def test_axial_slice_of_a_ras_volume_flips_x_and_y_into_lps() -> None:
    """A slice of an axis-aligned RAS volume: LPS read/phase are -x and -y, position the negated centre
    (pixel (2.5, 1.5) of 5 x 3)."""
    affine = np.diag([1.0, 2.0, 3.0, 1.0])
    affine[:3, 3] = (10.0, 20.0, 30.0)
    image = image_from_slice(np.zeros((5, 3), np.float32), affine)
    assert list(image.read_dir) == [-1.0, 0.0, 0.0] and list(image.phase_dir) == [0.0, -1.0, 0.0]
    assert list(image.slice_dir) == [0.0, 0.0, 1.0]
    assert list(image.position) == [-12.5, -23.0, 30.0]


def header(**fields: object) -> ismrmrd.ImageHeader:
    h = ismrmrd.ImageHeader()
    h.matrix_size[:] = (8, 8, 1)
    h.channels, h.image_type, h.data_type = 1, ismrmrd.IMTYPE_MAGNITUDE, ismrmrd.DATATYPE_FLOAT
    h.field_of_view[:] = (8.0, 8.0, 3.0)
    h.read_dir[:], h.phase_dir[:], h.slice_dir[:] = (1, 0, 0), (0, 1, 0), (0, 0, 1)
    for name, value in fields.items():
        setattr(h, name, value)
    return h


@pytest.mark.parametrize(("fields", "named"), [
    ({"image_type": ismrmrd.IMTYPE_PHASE}, "image_type: phase"),
    ({"image_type": ismrmrd.IMTYPE_COMPLEX}, "image_type: complex"),
    ({"channels": 4}, "channels: 4"),
    ({"data_type": ismrmrd.DATATYPE_CXFLOAT}, "data_type"),
    ({"field_of_view": (8.0, 8.0, 0.0)}, "field_of_view"),
    ({"phase_dir": (1.0, 0.0, 0.0)}, "read_dir, phase_dir, slice_dir"),
    ({"matrix_size": (8, 8, 3)}, "matrix_size: a 3D image"),
])
def test_unusable_headers_are_named(fields: dict, named: str) -> None:
    with pytest.raises(UnusableImage, match=named):
        check_image(header(**fields))


def test_a_real_image_type_and_integer_pixels_are_taken() -> None:
    check_image(header(image_type=ismrmrd.IMTYPE_REAL, data_type=ismrmrd.DATATYPE_USHORT))
    assert pixel_count(header(channels=2, matrix_size=(8, 8, 3))) == 384


def test_an_unset_image_type_with_real_pixels_is_taken_as_magnitude() -> None:
    """``ismrmrd.Image.from_array`` leaves ``image_type`` 0: an integrator's first images are not
    refused for it; complex pixels still are, by their data type."""
    assert ismrmrd.Image.from_array(np.zeros((1, 1, 4, 4), np.uint16)).image_type == 0
    check_image(header(image_type=0, data_type=ismrmrd.DATATYPE_USHORT))
    with pytest.raises(UnusableImage, match="data_type"):
        check_image(header(image_type=0, data_type=ismrmrd.DATATYPE_CXFLOAT))


def test_pose_meta_keeps_the_image_and_its_own_meta() -> None:
    image = image_from_slice(np.arange(6, dtype=np.uint16).reshape(3, 2), np.eye(4), series=1, slice_index=2)
    image.meta = {"ImageComments": "kept", "SVRnet.Accepted": "stale"}
    afv = np.arange(16, dtype=np.float64).reshape(4, 4) / 7.0
    pose = {"stack": "1", "index": 2, "accepted": False, "reason": "high_variance", "expected_error_mm": 4.25,
            "geodesic_variance": 0.125, "atlas_from_voxel": afv.tolist(), "translation_mm": [1.5, -2.0, 3.0],
            "latency_ms": 17.0}
    back = wire(with_pose(image, pose))
    np.testing.assert_array_equal(back.data, image.data)
    assert bytes(back.getHead())[:-4] == bytes(image.getHead())[:-4]   # all but attribute_string_len
    assert back.meta["ImageComments"] == "kept"
    assert set(POSE_META_KEYS.values()) <= set(back.meta)
    read = pose_from_meta(back.meta)
    assert read["accepted"] is False and read["reason"] == "high_variance"
    assert read["expected_error_mm"] == 4.25 and read["latency_ms"] == 17.0
    np.testing.assert_array_equal(read["atlas_from_voxel"], afv)      # exact: numbers written round-trip
    assert read["translation_mm"] == [1.5, -2.0, 3.0]


def test_pose_meta_of_an_accepted_slice_without_expected_error() -> None:
    image = image_from_slice(np.zeros((2, 2), np.float32), np.eye(4))
    read = pose_from_meta(wire(with_pose(image, {"accepted": True, "reason": None, "expected_error_mm": None})).meta)
    assert read == {"accepted": True, "reason": None, "expected_error_mm": None}
