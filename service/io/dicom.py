"""Single DICOM files with pydicom: classic single-frame, Enhanced multi-frame and Siemens mosaic.

Only pixel data and geometry are taken, and of the frames' acquisition times only their order
(:mod:`service.io.acquisition_times`); no identifying attribute is read into the result or logged
(de-identification on read). Geometry (LPS, converted to RAS in
:mod:`service.geometry.frames`):

* Enhanced multi-frame: per-frame ``PlanePositionSequence`` positions, shared or per-frame
  orientation and pixel measures (else the file's own tags); the frames must make one stack, as a
  zipped series' files must (:func:`~service.io.acquisition_geometry.series_problem`: one
  orientation and pixel spacing, evenly spaced along the normal, none shifted in its plane). Without
  per-frame positions the frames are stacked by ``SpacingBetweenSlices`` (or ``SliceThickness``)
  along the normal of the file's ``ImageOrientationPatient`` from its ``ImagePositionPatient`` (against
  the normal where the spacing is negative, as older scanners write frames stored downwards); a file
  missing any of these is refused, never given a made-up grid. Frames placed one by one are ordered
  along the slice normal, as a series' files are; frames stacked by a negative spacing keep the
  file's order, the affine's slice axis pointing against the normal.
* Siemens mosaic (``ImageType`` contains ``MOSAIC``): ``NumberOfImagesInMosaic`` (0019,100A) tiles
  in a square of ``ceil(sqrt(n))`` tiles a side, each the mosaic's size over that (as nibabel reads
  them; ``AcquisitionMatrix`` is the acquired matrix, smaller than the tiles at partial phase
  resolution); the position of the first tile is corrected from the mosaic's top-left corner by half
  the size difference (as dcm2niix and nibabel do). A count that does not divide the mosaic into
  tiles, leaves images in the tiles after the n-th or counts an empty tile, is refused. The tiles
  follow one another along the Siemens CSA image header's ``SliceNormalVector`` (0029,1010; read
  with nibabel's CSA reader, as nibabel and dcm2niix place them): the cross product of the row and
  column directions for slices stored in ascending order, its opposite for descending ones. A
  mosaic whose CSA header was stripped (anonymised) is taken as ascending; one whose header cannot
  be read, or whose normal is not along the image's, is refused. The header's ``MosaicRefAcqTimes``
  give the order the tiles were acquired in (an interleaved mosaic's, as a series' times do).
"""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
from pydicom.errors import InvalidDicomError

from service.core.errors import UnsupportedFile, UnusableImage
from service.geometry import frames
from service.io.acquisition_geometry import series_problem, stated_thickness
from service.io.acquisition_times import order_of, seconds
from service.io.dicom_guard import load_dataset
from service.io.limits import FileBudget, raise_if_out_of_space
from service.io.volume import Volume

with warnings.catch_warnings():         # nibabel.nicom warns on import about its DICOM readers, not used here
    warnings.simplefilter("ignore", UserWarning)
    from nibabel.nicom import csareader

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
    ds = None
    try:
        ds = load_dataset(path, filename, budget)
        pixels = ds.pixel_array.astype(np.float32)
    except (InvalidDicomError, AttributeError, ValueError, OSError, KeyError, EOFError) as exc:
        raise_if_out_of_space(exc)
        raise UnsupportedFile(f"{filename}: unreadable DICOM pixel data") from exc
    except (RuntimeError, NotImplementedError) as exc:       # pydicom has no decoder for its compression
        if ds is None:
            raise
        syntax = ds.file_meta.get("TransferSyntaxUID")
        named = getattr(syntax, "name", None) or "its transfer syntax"
        raise UnsupportedFile(f"{filename}: DICOM pixel data compressed as {named}, which this server cannot "
                              "decode as one multi-frame file; send the series as single-frame files in a ZIP, or "
                              "uncompressed") from exc
    slope = float(getattr(ds, "RescaleSlope", 1) or 1)
    pixels = pixels * slope + float(getattr(ds, "RescaleIntercept", 0) or 0)
    image_type = [str(t).upper() for t in getattr(ds, "ImageType", [])]
    if "MOSAIC" in image_type and NUMBER_OF_IMAGES_IN_MOSAIC in ds:
        return _mosaic(ds, pixels, filename)
    if pixels.ndim == 2:
        pixels = pixels[None]
    if pixels.ndim != 3:
        raise UnusableImage(f"{filename}: DICOM pixel data with {pixels.ndim} dimensions")
    return _multiframe(ds, pixels, filename)


def _orientation(values) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001 - an ImageOrientationPatient value
    iop = np.asarray(values, dtype=np.float64)
    if iop.shape != (6,) or not np.isfinite(iop).all():
        raise ValueError(f"ImageOrientationPatient holds {iop.size} values, not 6 finite numbers")
    return iop[:3], iop[3:]


def _multiframe(ds, pixels: np.ndarray, filename: str) -> Volume:  # noqa: ANN001
    shared = ds.SharedFunctionalGroupsSequence[0] if "SharedFunctionalGroupsSequence" in ds else None
    per_frame = ds.PerFrameFunctionalGroupsSequence if "PerFrameFunctionalGroupsSequence" in ds else None

    def group(name: str, frame: int = 0):  # noqa: ANN202
        for source in ((per_frame[frame] if per_frame is not None and frame < len(per_frame) else None), shared):
            if source is not None and name in source and len(source[name].value):
                return source[name].value[0]
        return None

    def tag(item, name: str):  # noqa: ANN001, ANN202 - a value of the functional group, else of the file
        return getattr(item, name, None) if item is not None and name in item else getattr(ds, name, None)

    n = len(pixels)
    if "RescaleSlope" not in ds and "RescaleIntercept" not in ds:      # Enhanced MR: each frame's own rescale
        for f in range(n):
            transform = group("PixelValueTransformationSequence", f)
            if transform is not None:
                pixels[f] = (pixels[f] * float(getattr(transform, "RescaleSlope", 1) or 1)
                             + float(getattr(transform, "RescaleIntercept", 0) or 0))
    placed = [group("PlanePositionSequence", f) for f in range(n)]     # a frame's own position, never the file's
    tags = [(getattr(placed[f], "ImagePositionPatient", None),
             tag(group("PlaneOrientationSequence", f), "ImageOrientationPatient"),
             tag(group("PixelMeasuresSequence", f), "PixelSpacing")) for f in range(n)]
    frame_times = [seconds(ds, group("FrameContentSequence", f)) for f in range(n)]
    by_frame = n > 1 and any(position is not None for position, _, _ in tags)
    if by_frame:                # frames placed one by one: they must make one stack, as a series' files must
        if (problem := series_problem(tags, "frames")) is not None:
            raise UnusableImage(f"{filename}: a multi-frame DICOM of {n} frames, but {problem}")
    else:                       # one position for the file: a single frame, or frames SpacingBetweenSlices apart
        measures = group("PixelMeasuresSequence")      # Enhanced MR states both there, a classic file at its top
        between = tag(measures, "SpacingBetweenSlices") or tag(measures, "SliceThickness")
        tags[0] = (tags[0][0] or getattr(ds, "ImagePositionPatient", None), tags[0][1], tags[0][2])
        missing = [name for name, value in zip(("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing"),
                                               tags[0]) if value is None]
        missing += ["SpacingBetweenSlices"] if n > 1 and between is None else []
        if missing:
            raise UnusableImage(f"{filename}: a DICOM image without {', '.join(missing)}: its geometry is unknown")
        if (problem := series_problem(tags[:1], "frames")) is not None:
            raise UnusableImage(f"{filename}: {problem}")
    row_dir, col_dir = _orientation(tags[0][1])
    normal = np.cross(row_dir, col_dir)
    if by_frame:
        along = np.array([np.asarray(p, np.float64) @ normal for p, _, _ in tags])
        order = np.argsort(along)
        pixels, frame_times = pixels[order], [frame_times[i] for i in order]
        dz, origin = float(np.median(np.diff(along[order]))), np.asarray(tags[order[0]][0], np.float64)
    else:
        dz, origin = float(between) if n > 1 else 1.0, np.asarray(tags[0][0], np.float64)
    if n > 1 and not (np.isfinite(dz) and dz != 0):
        raise UnusableImage(f"{filename}: a DICOM image of {n} frames {dz:g} mm apart (SpacingBetweenSlices, "
                            "SliceThickness or the frames' positions): its slice spacing is unknown")
    ps = [float(x) for x in tags[0][2]]
    lps = _lps_affine(row_dir, col_dir, normal, (ps[1], ps[0], dz), origin)    # a negative spacing: frames run against the normal
    thickness = stated_thickness([tag(group("PixelMeasuresSequence", f), "SliceThickness") for f in range(n)])
    return Volume(np.ascontiguousarray(pixels.transpose(2, 1, 0)), frames.ras_affine_from_lps(lps),
                  order_of(frame_times), slice_thickness_mm=thickness)


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
    tags = [(getattr(ds, "ImagePositionPatient", None), getattr(ds, "ImageOrientationPatient", None),
             getattr(ds, "PixelSpacing", None))]
    if (problem := series_problem(tags, "frames")) is not None:     # as a classic file's are checked
        raise UnusableImage(f"{filename}: {problem}")
    row_dir, col_dir = _orientation(getattr(ds, "ImageOrientationPatient", None))
    ps = [float(x) for x in ds.PixelSpacing]
    stated_normal, tile_times = _csa_slices(ds, n, filename)
    normal = _mosaic_normal(stated_normal, np.cross(row_dir, col_dir), filename)
    # ImagePositionPatient is the top-left of the whole mosaic: move to the first tile's corner.
    origin = np.asarray(ds.ImagePositionPatient, dtype=np.float64)
    origin = origin + row_dir * ps[1] * (cols - tc) / 2.0 + col_dir * ps[0] * (rows - tr) / 2.0
    dz = abs(float(getattr(ds, "SpacingBetweenSlices", None) or ds.SliceThickness))   # the CSA normal gives the way
    lps = _lps_affine(row_dir, col_dir, normal, (ps[1], ps[0], dz), origin)
    return Volume(np.ascontiguousarray(stack.transpose(2, 1, 0)), frames.ras_affine_from_lps(lps),
                  order_of(tile_times),
                  slice_thickness_mm=stated_thickness([getattr(ds, "SliceThickness", None)]))


def _csa_slices(ds, n: int, filename: str) -> tuple[np.ndarray | None, list[float | None]]:  # noqa: ANN001
    """What the Siemens CSA image header (0029,1010; nibabel's reader) says of a mosaic's ``n`` tiles:
    its ``SliceNormalVector`` (``None``: no header, or no normal in it) and each tile's acquisition
    time within the repetition (``MosaicRefAcqTimes``, ms -> s; ``None`` where the header does not
    give all ``n``: the order of an interleaved mosaic)."""
    try:
        csa = csareader.get_csa_header(ds, "image")
        stated = None if csa is None else csareader.get_slice_normal(csa)
        normal = None if stated is None else np.asarray(stated, np.float64)
    except (csareader.CSAReadError, struct.error, AssertionError, ValueError, TypeError, KeyError) as exc:
        raise UnusableImage(f"{filename}: the mosaic's Siemens CSA image header (0029,1010) cannot be read, so "
                            "the order of its slices is unknown") from exc
    items = ((csa or {}).get("tags", {}).get("MosaicRefAcqTimes") or {}).get("items") or []
    if len(items) < n or not all(isinstance(t, (int, float)) and np.isfinite(t) for t in items[:n]):
        return normal, [None] * n
    return normal, [float(t) / 1000.0 for t in items[:n]]


def _mosaic_normal(stated: np.ndarray | None, image_normal: np.ndarray, filename: str) -> np.ndarray:
    """The direction in which a mosaic's tiles follow one another: the CSA image header's
    ``SliceNormalVector`` ``stated`` where the file has one (``image_normal`` or its opposite), else
    ``image_normal`` (the row and column directions' cross product: slices taken as ascending)."""
    if stated is None:
        return image_normal
    along = float(stated @ image_normal) / max(float(np.linalg.norm(stated)), 1e-12)
    if not np.isfinite(along) or abs(along) < 0.99:                       # within about 8 degrees
        raise UnusableImage(f"{filename}: the mosaic's CSA SliceNormalVector {np.round(stated, 4).tolist()} does "
                            "not lie along the normal of its ImageOrientationPatient")
    return image_normal if along > 0 else -image_normal
