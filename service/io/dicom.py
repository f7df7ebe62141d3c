"""Single DICOM files with pydicom: classic single-frame, Enhanced multi-frame and Siemens mosaic.

Only pixel data and geometry are taken, and of the frames' acquisition times only their order
(:mod:`service.io.acquisition_times`); no identifying attribute is read into the result or logged
(de-identification on read). Geometry (LPS, converted to RAS in
:mod:`service.geometry.frames`):

* Enhanced multi-frame: per-frame ``PlanePositionSequence`` positions, shared or per-frame
  orientation and pixel measures; without functional groups (rare, truncated files) the frames
  are stacked with ``SpacingBetweenSlices`` along the normal of an identity orientation.
* Siemens mosaic (``ImageType`` contains ``MOSAIC``): ``NumberOfImagesInMosaic`` (0019,100A) tiles
  in a square of ``ceil(sqrt(n))`` tiles a side, each the mosaic's size over that (as nibabel reads
  them; ``AcquisitionMatrix`` is the acquired matrix, smaller than the tiles at partial phase
  resolution); the position of the first tile is corrected from the mosaic's top-left corner by half
  the size difference (as dcm2niix and nibabel do). A count that does not divide the mosaic into
  tiles, leaves images in the tiles after the n-th or counts an empty tile, is refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydicom.errors import InvalidDicomError

from service.core.errors import UnsupportedFile, UnusableImage
from service.geometry import frames
from service.io.acquisition_times import order_of, seconds
from service.io.dicom_guard import load_dataset
from service.io.limits import FileBudget
from service.io.volume import Volume

NUMBER_OF_IMAGES_IN_MOSAIC = (0x0019, 0x100A)


def _lps_affine(row_dir: np.ndarray, col_dir: np.ndarray, normal: np.ndarray, spacing: tuple[float, float, float],
                origin: np.ndarray) -> np.ndarray:
    """Voxel (i = column, j = row, k = frame) -> LPS affine."""
    a = np.eye(4)
    a[:3, 0] = row_dir * spacing[0]     # along a row: next column
    a[:3, 1] = col_dir * spacing[1]     # along a column: next row
    a[:3, 2] = normal * spacing[2]
    a[:3, 3] = origin
    return a


def read_dicom_file(path: Path, filename: str, budget: FileBudget) -> Volume:
    """Read one DICOM file as a 3D :class:`Volume` (array ``[i, j, k]`` = column, row, frame).

    ``filename`` is the client's name of the file (for a ZIP member: ``archive.zip: member``); every
    decoder is bounded by ``budget`` (:mod:`service.io.dicom_guard`).
    """
    try:
        ds = load_dataset(path, filename, budget)
        pixels = ds.pixel_array.astype(np.float32)
    except (InvalidDicomError, AttributeError, ValueError, OSError, KeyError, EOFError) as exc:
        raise UnsupportedFile(f"{filename}: unreadable DICOM pixel data") from exc
    slope = float(getattr(ds, "RescaleSlope", 1) or 1)
    pixels = pixels * slope + float(getattr(ds, "RescaleIntercept", 0) or 0)
    image_type = [str(t).upper() for t in getattr(ds, "ImageType", [])]
    if "MOSAIC" in image_type and NUMBER_OF_IMAGES_IN_MOSAIC in ds:
        return _mosaic(ds, pixels, filename)
    if pixels.ndim == 2:
        pixels = pixels[None]
    if pixels.ndim != 3:
        raise UnusableImage(f"{filename}: DICOM pixel data with {pixels.ndim} dimensions")
    return _multiframe(ds, pixels)


def _orientation(item) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001 - a pydicom dataset
    iop = np.asarray(item.ImageOrientationPatient, dtype=np.float64)
    if iop.shape != (6,) or not np.isfinite(iop).all():
        raise ValueError(f"ImageOrientationPatient holds {iop.size} values, not 6 finite numbers")
    return iop[:3], iop[3:]


def _multiframe(ds, pixels: np.ndarray) -> Volume:  # noqa: ANN001
    shared = ds.SharedFunctionalGroupsSequence[0] if "SharedFunctionalGroupsSequence" in ds else None
    per_frame = ds.PerFrameFunctionalGroupsSequence if "PerFrameFunctionalGroupsSequence" in ds else None

    def group(name: str, frame: int = 0):  # noqa: ANN202
        for source in ((per_frame[frame] if per_frame is not None else None), shared):
            if source is not None and name in source:
                return source[name].value[0]
        return None

    orient, measures = group("PlaneOrientationSequence"), group("PixelMeasuresSequence")
    if orient is not None:
        row_dir, col_dir = _orientation(orient)
    elif "ImageOrientationPatient" in ds:
        row_dir, col_dir = _orientation(ds)
    else:
        row_dir, col_dir = np.array([1.0, 0, 0]), np.array([0.0, 1, 0])
    src = measures if measures is not None and "PixelSpacing" in measures else ds
    ps = [float(x) for x in getattr(src, "PixelSpacing", [1.0, 1.0])]
    normal = np.cross(row_dir, col_dir)
    frame_times = [seconds(ds, group("FrameContentSequence", f)) for f in range(len(pixels))]
    positions = []
    for f in range(len(pixels)):
        pos = group("PlanePositionSequence", f)
        if pos is None:
            break
        positions.append(np.asarray(pos.ImagePositionPatient, dtype=np.float64))
    if len(positions) == len(pixels) and len(pixels) > 1:
        order = np.argsort([p @ normal for p in positions])
        pixels = pixels[order]
        positions = [positions[i] for i in order]
        frame_times = [frame_times[i] for i in order]
        dz = float(np.median(np.diff([p @ normal for p in positions])))
        origin = positions[0]
    else:
        dz = float(getattr(ds, "SpacingBetweenSlices", None) or getattr(ds, "SliceThickness", None) or 1.0)
        origin = np.asarray(getattr(ds, "ImagePositionPatient", [0.0, 0.0, 0.0]), dtype=np.float64)
    lps = _lps_affine(row_dir, col_dir, normal, (ps[1], ps[0], abs(dz) or 1.0), origin)
    return Volume(np.ascontiguousarray(pixels.transpose(2, 1, 0)), frames.ras_affine_from_lps(lps),
                  order_of(frame_times))


def _mosaic(ds, pixels: np.ndarray, filename: str) -> Volume:  # noqa: ANN001
    n = int(ds[NUMBER_OF_IMAGES_IN_MOSAIC].value)
    rows, cols = pixels.shape
    tiles_per_row = int(np.ceil(np.sqrt(max(n, 1))))
    tr, tc = rows // tiles_per_row, cols // tiles_per_row
    # A Siemens mosaic is ceil(sqrt(n)) tiles of the reconstructed matrix on each side, exactly; the
    # unused tiles after the n-th are empty. Any other layout means n is not this mosaic's count, and
    # tiles cut at the wrong size would mix slices silently.
    if n < 1 or min(tr, tc) < 2 or rows % tiles_per_row or cols % tiles_per_row:
        raise UnusableImage(f"{filename}: NumberOfImagesInMosaic {n} does not fit a mosaic of {rows} x {cols} pixels "
                            f"({tiles_per_row} x {tiles_per_row} tiles)")
    acquired = [int(x) for x in getattr(ds, "AcquisitionMatrix", None) or [] if int(x) > 0]
    if acquired and max(acquired) > max(tr, tc):
        raise UnusableImage(f"{filename}: NumberOfImagesInMosaic {n} makes tiles of {tr} x {tc} pixels, smaller than "
                            f"the acquired matrix {max(acquired)}")
    tiles = pixels.reshape(tiles_per_row, tr, tiles_per_row, tc).transpose(0, 2, 1, 3).reshape(-1, tr, tc)
    if np.any(tiles[n:]):
        raise UnusableImage(f"{filename}: the mosaic holds images beyond its NumberOfImagesInMosaic {n}")
    empty = np.flatnonzero(~tiles[:n].any(axis=(1, 2)))
    if empty.size:
        raise UnusableImage(f"{filename}: tile {empty[0]} of the mosaic's {n} images (NumberOfImagesInMosaic) is empty")
    stack = tiles[:n]
    row_dir, col_dir = _orientation(ds)
    ps = [float(x) for x in ds.PixelSpacing]
    normal = np.cross(row_dir, col_dir)
    # ImagePositionPatient is the top-left of the whole mosaic: move to the first tile's corner.
    origin = np.asarray(ds.ImagePositionPatient, dtype=np.float64)
    origin = origin + row_dir * ps[1] * (cols - tc) / 2.0 + col_dir * ps[0] * (rows - tr) / 2.0
    dz = float(getattr(ds, "SpacingBetweenSlices", None) or ds.SliceThickness)
    lps = _lps_affine(row_dir, col_dir, normal, (ps[1], ps[0], dz), origin)
    return Volume(np.ascontiguousarray(stack.transpose(2, 1, 0)), frames.ras_affine_from_lps(lps))
