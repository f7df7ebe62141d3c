"""MRD (ISMRMRD) images <-> the streaming core's 2D slices, and a slice's pose as image meta attributes.

An MRD image stores its pixels as ``data[channel, z, y, x]`` with ``x`` along ``read_dir`` (readout)
and ``y`` along ``phase_dir``; ``position`` is the centre of the image (not of its first pixel) in
the scanner's **LPS** patient frame, ``field_of_view`` is ``(read, phase, slice thickness)`` in mm.
The service's slice is ``pixels[i0, i1]`` with ``i0 = x``, ``i1 = y`` and a ``scanner_from_voxel``
that maps ``(i0, i1, 0, 1)`` to scanner **RAS** mm (third column: the normal times the thickness).
LPS meets RAS in :mod:`service.geometry.frames`, nowhere else.

Example:
    >>> import numpy as np
    >>> a = np.diag([-1.25, 1.25, 3.0, 1.0]); a[:3, 3] = (10.0, -20.0, 5.0)
    >>> img = image_from_slice(np.arange(12, dtype=np.float32).reshape(4, 3), a, series=2, slice_index=7)
    >>> tuple(img.matrix_size), img.image_series_index, img.slice
    ((4, 3, 1), 2, 7)
    >>> pixels, back = slice_from_image(img)
    >>> pixels.shape, bool(np.allclose(back, a)), float(pixels[3, 1])
    ((4, 3), True, 10.0)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import ismrmrd
import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.errors import UnusableImage
from service.geometry import frames

ACCEPTED_IMAGE_TYPES = {ismrmrd.IMTYPE_MAGNITUDE: "magnitude", ismrmrd.IMTYPE_REAL: "real", 0: "unset"}
"""The image types taken: magnitude, real, and 0 (unset, as ``ismrmrd.Image.from_array`` leaves it),
whose real-valued pixels (:data:`REAL_DATA_TYPES`, checked apart) are taken as a magnitude image's."""
IMAGE_TYPE_NAMES = {ismrmrd.IMTYPE_PHASE: "phase", ismrmrd.IMTYPE_IMAG: "imaginary",
                    ismrmrd.IMTYPE_COMPLEX: "complex", ismrmrd.IMTYPE_RGB: "rgb", **ACCEPTED_IMAGE_TYPES}
REAL_DATA_TYPES = {ismrmrd.DATATYPE_USHORT, ismrmrd.DATATYPE_SHORT, ismrmrd.DATATYPE_UINT,
                   ismrmrd.DATATYPE_INT, ismrmrd.DATATYPE_FLOAT, ismrmrd.DATATYPE_DOUBLE}
DIRECTION_TOLERANCE = 1e-3
"""How far (``|d| - 1``, pairwise dot products) the header's float32 direction cosines may be from
an orthonormal frame."""

POSE_META_KEYS = {
    "accepted": "SVRnet.Accepted",
    "reason": "SVRnet.Reason",
    "expected_error_mm": "SVRnet.ExpectedErrorMM",
    "geodesic_variance": "SVRnet.GeodesicVariance",
    "atlas_from_voxel": "SVRnet.AtlasFromVoxel",
    "translation_mm": "SVRnet.TranslationMM",
    "latency_ms": "SVRnet.LatencyMS",
}
"""Field of a ``pose`` body (Stream v1) -> the meta attribute that carries it back to the scanner."""


def pixel_count(header: ismrmrd.ImageHeader | ismrmrd.Image) -> int:
    """Values an image header announces (channels x x x y x z): what reading its data allocates.

    Example:
        >>> h = ismrmrd.ImageHeader(); h.matrix_size[:] = (64, 48, 1); h.channels = 2
        >>> pixel_count(h)
        6144
    """
    matrix = tuple(header.matrix_size)
    return int(header.channels) * int(matrix[0]) * int(matrix[1]) * int(matrix[2])


def shape_problem(header: ismrmrd.ImageHeader | ismrmrd.Image) -> UnusableImage | None:
    """What makes an image's announced shape unusable (a volume, or several channels: the streaming
    core takes 2D one-channel images), else None; known from the header alone, before the data.

    Example:
        >>> h = ismrmrd.ImageHeader(); h.matrix_size[:] = (8, 8, 1); h.channels = 4
        >>> shape_problem(h)
        UnusableImage('channels: 4; svrnet-mrd takes one-channel (coil-combined) images')
    """
    nx, ny, nz = (int(n) for n in header.matrix_size)
    if nz > 1:
        return UnusableImage(f"matrix_size: a 3D image ({nx} x {ny} x {nz}); svrnet-mrd takes 2D images")
    if nz < 1:
        return UnusableImage(f"matrix_size: an empty image ({nx} x {ny} x {nz})")
    if int(header.channels) != 1:
        return UnusableImage(f"channels: {int(header.channels)}; svrnet-mrd takes one-channel (coil-combined) images")
    return None


def check_image(header: ismrmrd.ImageHeader | ismrmrd.Image) -> None:
    """Raise :class:`UnusableImage` naming the field of a header the streaming core cannot use:
    not a 2D one-channel real magnitude (or real) image, or no usable geometry.

    Example:
        >>> h = ismrmrd.ImageHeader(); h.matrix_size[:] = (8, 8, 4); h.channels = 1
        >>> check_image(h)
        Traceback (most recent call last):
        ...
        service.core.errors.UnusableImage: matrix_size: a 3D image (8 x 8 x 4); svrnet-mrd takes 2D images
    """
    if problem := shape_problem(header):
        raise problem
    nx, ny, _ = (int(n) for n in header.matrix_size)
    if nx < 1 or ny < 1:
        raise UnusableImage(f"matrix_size: an empty image ({nx} x {ny})")
    if int(header.image_type) not in ACCEPTED_IMAGE_TYPES:
        name = IMAGE_TYPE_NAMES.get(int(header.image_type), f"code {int(header.image_type)}")
        raise UnusableImage(f"image_type: {name}; svrnet-mrd takes magnitude or real images")
    if int(header.data_type) not in REAL_DATA_TYPES:
        raise UnusableImage(f"data_type: code {int(header.data_type)}; svrnet-mrd takes real-valued pixels")
    fov = np.asarray(header.field_of_view, dtype=np.float64)
    if not (np.all(np.isfinite(fov)) and np.all(fov > 0)):
        raise UnusableImage("field_of_view: read, phase and slice thickness must be positive mm")
    if not np.all(np.isfinite(np.asarray(header.position, dtype=np.float64))):
        raise UnusableImage("position: not finite")
    directions = np.array([header.read_dir, header.phase_dir, header.slice_dir], dtype=np.float64)
    if not (np.all(np.isfinite(directions))
            and np.allclose(directions @ directions.T, np.eye(3), atol=DIRECTION_TOLERANCE)):
        raise UnusableImage("read_dir, phase_dir, slice_dir: not an orthonormal frame")


@dataclass(frozen=True)
class SliceGeometry:
    """The geometry fields of a 2D MRD image header, in float64 (the header itself holds float32).

    ``position`` is the image's centre in scanner LPS mm; ``read_dir``, ``phase_dir``, ``slice_dir``
    are unit vectors in LPS; ``field_of_view`` is ``(read, phase, slice thickness)`` in mm.
    """

    matrix_size: tuple[int, int]
    field_of_view: tuple[float, float, float]
    position: tuple[float, float, float]
    read_dir: tuple[float, float, float]
    phase_dir: tuple[float, float, float]
    slice_dir: tuple[float, float, float]

    @classmethod
    def of_header(cls, header: ismrmrd.ImageHeader | ismrmrd.Image) -> "SliceGeometry":
        """The geometry an image header states."""
        def triple(values: Any) -> tuple[float, float, float]:
            return tuple(float(v) for v in values)  # type: ignore[return-value]

        return cls((int(header.matrix_size[0]), int(header.matrix_size[1])), triple(header.field_of_view),
                   triple(header.position), triple(header.read_dir), triple(header.phase_dir),
                   triple(header.slice_dir))

    @classmethod
    def of_slice(cls, shape: tuple[int, int], scanner_from_voxel: ArrayLike) -> "SliceGeometry":
        """The header geometry of a slice ``[x, y]`` of ``shape`` placed by a RAS ``scanner_from_voxel``
        (MRD's directions and pixel sizes are ITK's, :func:`~service.geometry.frames.itk_from_affine`;
        :class:`ValueError` for a sheared one)."""
        origin, spacing, direction = frames.itk_from_affine(scanner_from_voxel)
        nx, ny = int(shape[0]), int(shape[1])
        centre = origin + direction[:, :2] @ (spacing[:2] * centre_voxel(nx, ny))
        return cls((nx, ny), (spacing[0] * nx, spacing[1] * ny, spacing[2]), tuple(centre.tolist()),
                   *(tuple(direction[:, c].tolist()) for c in range(3)))  # type: ignore[arg-type]

    def scanner_from_voxel(self) -> NDArray[np.float64]:
        """Voxel ``(x, y, 0, 1)`` -> scanner RAS mm.

        Column 0 is ``read_dir`` times the read pixel size ``field_of_view[0] / matrix_size[0]``, column
        1 ``phase_dir`` times ``field_of_view[1] / matrix_size[1]``, column 2 ``slice_dir`` times the
        slice thickness ``field_of_view[2]``; ``position``, the image's centre, lies at voxel
        :func:`centre_voxel`.

        Example:
            >>> g = SliceGeometry((4, 3), (5.0, 3.0, 2.0), (0.0, 0.0, 0.0), (1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0))
            >>> g.scanner_from_voxel()[:3, 3].tolist()        # LPS (-2 * 1.25, -1.5, 0) -> RAS
            [2.5, 1.5, 0.0]
        """
        nx, ny = self.matrix_size
        fov = np.asarray(self.field_of_view, dtype=np.float64)
        spacing = np.array([fov[0] / nx, fov[1] / ny, fov[2]])
        direction = np.stack([self.read_dir, self.phase_dir, self.slice_dir], axis=1).astype(np.float64)
        origin = np.asarray(self.position) - direction[:, :2] @ (spacing[:2] * centre_voxel(nx, ny))
        return frames.affine_from_itk(origin, spacing, direction)

    def write_into(self, image: ismrmrd.Image) -> None:
        """Set the geometry fields of ``image``'s header (rounded to the header's float32)."""
        image.field_of_view, image.position = self.field_of_view, self.position
        image.read_dir, image.phase_dir, image.slice_dir = self.read_dir, self.phase_dir, self.slice_dir


def centre_voxel(nx: int, ny: int) -> NDArray[np.float64]:
    """Where an MRD image's ``position`` lies in its pixel grid: ``(nx / 2, ny / 2)``, the centre of
    the field of view as the scanner's Fourier reconstruction places it (pixel ``n / 2`` of an even
    side, not between two pixels), and as Gadgetron writes a DICOM image's first pixel from it
    (``position - field_of_view / 2`` along ``read_dir`` and ``phase_dir``).

    Example:
        >>> centre_voxel(256, 224).tolist()
        [128.0, 112.0]
    """
    return np.array([nx / 2, ny / 2], dtype=np.float64)


def slice_from_image(image: ismrmrd.Image) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """An MRD image as the streaming core's slice: ``(pixels [x, y] float32, scanner_from_voxel)``,
    ``pixels[x, y]`` at scanner RAS ``scanner_from_voxel @ (x, y, 0, 1)``.

    Raises:
        UnusableImage: see :func:`check_image`.
    """
    check_image(image)
    pixels = np.asarray(image.data[0, 0], dtype=np.float32).T    # data is [channel, z, y, x]
    return np.ascontiguousarray(pixels), SliceGeometry.of_header(image).scanner_from_voxel()


def image_from_slice(pixels: ArrayLike, scanner_from_voxel: ArrayLike, series: int = 0, slice_index: int = 0,
                     image_index: int = 0) -> ismrmrd.Image:
    """The inverse of :func:`slice_from_image`: a 2D magnitude MRD image of ``pixels [x, y]`` whose
    header places voxel ``(x, y, 0, 1)`` where the RAS ``scanner_from_voxel`` says (test clients and
    the simulator send these).

    The header's fields are float32: positions keep about 1e-5 mm at 100 mm from the isocentre.
    """
    array = np.asarray(pixels)
    if array.ndim != 2:
        raise UnusableImage(f"pixels: a 2D array was expected, got {array.ndim} dimensions")
    image = ismrmrd.Image.from_array(np.ascontiguousarray(array.T), transpose=False)
    image.image_type = ismrmrd.IMTYPE_MAGNITUDE
    SliceGeometry.of_slice(array.shape, scanner_from_voxel).write_into(image)
    image.image_series_index, image.slice, image.image_index = series, slice_index, image_index
    return image


def _meta_value(value: Any) -> str | list[str]:
    """A pose field as meta text: numbers as Python prints them (round-trip exact), booleans 1/0, lists
    flattened row-major, ``None`` (no reason; a non-finite number) as ``""`` and ``"nan"``."""
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_meta_value(v) for v in np.asarray(value, dtype=np.float64).ravel().tolist()]  # type: ignore[misc]
    if isinstance(value, (int, float, np.number)):
        return repr(float(value)) if not isinstance(value, (int, np.integer)) else str(int(value))
    return "" if value is None else str(value)


def pose_meta(pose: Mapping[str, Any]) -> dict[str, str | list[str]]:
    """The ``SVRnet.*`` meta attributes of a ``pose`` body (fields absent from it are left out).

    Example:
        >>> m = pose_meta({"accepted": True, "reason": None, "expected_error_mm": None, "latency_ms": 12.5,
        ...                "translation_mm": [1.0, 2.0, 3.0]})
        >>> m["SVRnet.Accepted"], m["SVRnet.Reason"], m["SVRnet.ExpectedErrorMM"], m["SVRnet.TranslationMM"]
        ('1', '', 'nan', ['1.0', '2.0', '3.0'])
    """
    meta: dict[str, str | list[str]] = {}
    for field, key in POSE_META_KEYS.items():
        if field not in pose:
            continue
        value = pose[field]
        if value is None and field not in ("reason",):
            meta[key] = "nan"
        else:
            meta[key] = _meta_value(value)
    return meta


def with_pose(image: ismrmrd.Image, pose: Mapping[str, Any]) -> ismrmrd.Image:
    """The same image (header and data) with the pose's ``SVRnet.*`` meta attributes added to its own
    (an ``SVRnet.*`` attribute it already had is replaced)."""
    meta = ismrmrd.Meta()
    meta.update(image.meta)
    meta.update(pose_meta(pose))
    return ismrmrd.Image(head=image.getHead(), data=image.data, meta=meta)


def pose_from_meta(meta: Mapping[str, Any]) -> dict[str, Any]:
    """The pose fields back from an image's meta attributes (clients, tests): the inverse of
    :func:`pose_meta`, with ``atlas_from_voxel`` as a 4 x 4 list.

    Example:
        >>> m = ismrmrd.Meta.deserialize(ismrmrd.Meta(pose_meta({"accepted": False, "reason": "high_variance",
        ...                                                      "atlas_from_voxel": np.eye(4)})).serialize())
        >>> p = pose_from_meta(m); p["accepted"], p["reason"], p["atlas_from_voxel"][3]
        (False, 'high_variance', [0.0, 0.0, 0.0, 1.0])
    """
    pose: dict[str, Any] = {}
    for field, key in POSE_META_KEYS.items():
        if key not in meta:
            continue
        value = meta[key]
        if field == "accepted":
            pose[field] = value == "1"
        elif field == "reason":
            pose[field] = value or None
        elif field == "atlas_from_voxel":
            pose[field] = np.asarray(value, dtype=np.float64).reshape(4, 4).tolist()
        elif field == "translation_mm":
            pose[field] = np.asarray(value, dtype=np.float64).tolist()
        else:
            number = float(value)
            pose[field] = number if np.isfinite(number) else None
    return pose
