"""Hostile and valid uploads, generated (fixed seeds, no binary blobs in the repo): DICOM files with any
transfer syntax, decompression bombs, archives inside archives."""

from __future__ import annotations

import gzip
import io
import zipfile
import zlib

import numpy as np
from pydicom import uid
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom.filebase import DicomBytesIO
from pydicom.filewriter import write_dataset, write_file_meta_info

SERIES = "1.2.826.0.1.3680043.2.1125.7"


def _dataset(rows: int, cols: int, frames: int, k: int = 0) -> Dataset:
    ds = Dataset()
    ds.PatientName, ds.PatientID, ds.Modality = "Doe^Jane", "P-19840101", "MR"
    ds.SOPClassUID, ds.SOPInstanceUID = uid.MRImageStorage, f"{SERIES}.{k + 1}"
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.InstanceNumber = "1.2.826.0.1.3680043.2.1125.1", SERIES, k + 1
    ds.Rows, ds.Columns, ds.SamplesPerPixel, ds.PhotometricInterpretation = rows, cols, 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.ImagePositionPatient, ds.ImageOrientationPatient = [0.0, 0.0, 3.0 * k], [1.0, 0, 0, 0, 1.0, 0]
    ds.PixelSpacing, ds.SliceThickness, ds.SpacingBetweenSlices = [1.0, 1.0], 3.0, 3.0
    if frames > 1:
        ds.NumberOfFrames = frames
    return ds


def _file(ds: Dataset, ts: str, body: bytes | None = None) -> bytes:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = ds.SOPClassUID, ds.SOPInstanceUID
    meta.TransferSyntaxUID, meta.ImplementationClassUID = ts, "1.2.826.0.1.3680043.2.1125.99"
    fp = DicomBytesIO()
    fp.is_little_endian, fp.is_implicit_VR = True, False
    write_file_meta_info(fp, meta, enforce_standard=True)
    if body is None:
        out = DicomBytesIO()
        out.is_little_endian, out.is_implicit_VR = True, ts == uid.ImplicitVRLittleEndian
        write_dataset(out, ds)
        body = out.getvalue()
    return b"\0" * 128 + b"DICM" + fp.getvalue() + body


def dicom(pixels: np.ndarray, k: int = 0, ts: str = uid.ExplicitVRLittleEndian) -> bytes:
    """A valid MR DICOM file of uint16 ``pixels`` [frames, rows, cols] (or [rows, cols])."""
    p = np.asarray(pixels, np.uint16)
    p3 = p[None] if p.ndim == 2 else p
    ds = _dataset(p3.shape[1], p3.shape[2], p3.shape[0] if p.ndim == 3 else 1, k)
    ds.PixelData = p.tobytes()
    if ts == uid.DeflatedExplicitVRLittleEndian:
        return deflated(ds)
    return _file(ds, ts)


def deflated(ds: Dataset, zero_pixel_bytes: int = 0) -> bytes:
    """``ds`` as Deflated Explicit VR Little Endian; ``zero_pixel_bytes`` > 0 appends that many zero
    pixel bytes, streamed through the compressor (a deflate bomb costs the test no memory)."""
    out = DicomBytesIO()
    out.is_little_endian, out.is_implicit_VR = True, False
    write_dataset(out, ds)
    c = zlib.compressobj(9, zlib.DEFLATED, -zlib.MAX_WBITS)
    data = c.compress(out.getvalue())
    if zero_pixel_bytes:
        data += c.compress(b"\xe0\x7f\x10\x00OW\x00\x00" + zero_pixel_bytes.to_bytes(4, "little"))
        block = b"\0" * (1 << 20)
        for start in range(0, zero_pixel_bytes, len(block)):
            data += c.compress(block[: min(len(block), zero_pixel_bytes - start)])
    return _file(ds, uid.DeflatedExplicitVRLittleEndian, data + c.flush())


def deflate_bomb(megabytes: int = 256) -> bytes:
    """A DICOM whose deflated dataset holds ``megabytes`` MB of pixels (1024 x 1024 x n, 16 bit)."""
    frames = megabytes // 2
    return deflated(_dataset(1024, 1024, frames), 1024 * 1024 * 2 * frames)


def encapsulated(frames: list[bytes], rows: int, cols: int, ts: str) -> bytes:
    """A DICOM with encapsulated (compressed) pixel data made of ``frames`` as given."""
    ds = _dataset(rows, cols, len(frames))
    ds.PixelData = encapsulate(frames)
    out = DicomBytesIO()
    out.is_little_endian, out.is_implicit_VR = True, False
    write_dataset(out, ds)
    return _file(ds, ts, out.getvalue())


def jpeg_claiming(width: int, height: int) -> bytes:
    """A JPEG stream whose SOF0 says ``width x height`` (what a decoder would allocate)."""
    sof = b"\xff\xc0\x00\x0b\x08" + height.to_bytes(2, "big") + width.to_bytes(2, "big") + b"\x01\x01\x11\x00"
    return b"\xff\xd8" + sof + b"\xff\xd9"


def rle_bomb(pairs: int = 50_000) -> bytes:
    """One RLE segment of ``pairs`` (-127, 0) runs: 2 bytes each that decode to 128 zero bytes."""
    header = (1).to_bytes(4, "little") + (64).to_bytes(4, "little") + b"\0" * 56
    return header + b"\x81\x00" * pairs


def gzip_bomb(megabytes: int) -> bytes:
    """A gzip stream of ``megabytes`` MB of zeros behind a NIfTI-1 header that declares them."""
    n = megabytes * 2**20 // 4
    side = int(round(n ** (1 / 3)))
    head = bytearray(352)
    head[0:4] = (348).to_bytes(4, "little")
    head[40:56] = np.array([3, side, side, side, 1, 1, 1, 1], "<i2").tobytes()
    head[70:74] = np.array([16, 32], "<i2").tobytes()                 # float32
    head[76:108] = np.array([1, 1, 1, 1, 0, 0, 0, 0], "<f4").tobytes()
    head[108:112] = np.float32(352).tobytes()
    head[252:256] = np.array([1, 0], "<i2").tobytes()                # qform: scanner (identity), no sform
    head[344:348] = b"n+1\x00"
    buf = io.BytesIO()
    with gzip.GzipFile(fileobj=buf, mode="wb", compresslevel=9, mtime=0) as g:
        g.write(bytes(head))
        block, left = b"\0" * (1 << 20), side ** 3 * 4
        while left > 0:
            g.write(block[:left])
            left -= len(block)
    return buf.getvalue()


def zipped(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


def nifti(array: np.ndarray, pixdim: tuple[float, ...] = (1.0, 1.0, 3.0), magic: bytes = b"n+1\x00",
          dims: tuple[int, ...] | None = None) -> bytes:
    """An uncompressed NIfTI-1 file of float32 ``array`` (``dims`` overrides the declared dim field)."""
    a = np.asarray(array, np.float32)
    head = bytearray(352)
    head[0:4] = (348).to_bytes(4, "little")
    d = dims if dims is not None else (a.ndim, *a.shape)
    head[40:56] = np.array(list(d) + [1] * (8 - len(d)), "<i2").tobytes()
    head[70:74] = np.array([16, 32], "<i2").tobytes()
    head[76:108] = np.array([1, *pixdim, *[1.0] * (7 - len(pixdim))], "<f4").tobytes()
    head[108:112] = np.float32(352).tobytes()
    head[252:256] = np.array([1, 0], "<i2").tobytes()                # qform: scanner (identity), no sform
    head[344:348] = magic
    return bytes(head) + a.tobytes(order="F")


def gz(data: bytes) -> bytes:
    return gzip.compress(data, mtime=0)


def encrypted_zip(members: dict[str, bytes]) -> bytes:
    """A ZIP whose members claim to be encrypted (general-purpose flag bit 0)."""
    data = bytearray(zipped(members, zipfile.ZIP_STORED))
    for sig, flag_at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):
        at = data.find(sig)
        while at >= 0:
            data[at + flag_at] |= 1
            at = data.find(sig, at + 4)
    return bytes(data)
