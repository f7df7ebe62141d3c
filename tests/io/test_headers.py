"""A header can never make the server read one of its own files, however it is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from service.core.errors import PayloadTooLarge, UnsupportedFile
from service.io.headers import MAX_HEADER_BYTES
from service.io.readers import read_upload

COMMENTS = b"".join(b"# padding line %05d to push the field past any fixed-size peek\n" % i for i in range(1400))


def nrrd(data_file: bytes, comments: bytes = COMMENTS, field: bytes = b"data file") -> bytes:
    return (b"NRRD0004\n" + comments + b"type: uchar\ndimension: 3\nsizes: 8 8 8\nencoding: raw\n"
            + field + b": " + data_file + b"\n\n")


def mha(data_file: bytes, comments: bytes = b"", key: bytes = b"ElementDataFile") -> bytes:
    return (b"ObjectType = Image\nNDims = 3\n" + comments + b"DimSize = 8 8 8\nElementType = MET_UCHAR\n"
            + key + b" = " + data_file + b"\n")


@pytest.fixture
def secret(tmp_path: Path) -> Path:
    path = tmp_path / "server_secret.raw"
    path.write_bytes(bytes(range(256)) * 2)
    return path


def refuse(tmp_path: Path, content: bytes, name: str) -> str:
    upload = tmp_path / "upload.bin"
    upload.write_bytes(content)
    with pytest.raises(UnsupportedFile) as info:
        read_upload(upload, name)
    assert name in info.value.detail
    return info.value.detail


def test_an_nrrd_data_file_after_80_kb_of_comments_is_refused(tmp_path: Path, secret: Path) -> None:
    hostile = nrrd(str(secret).encode())
    assert len(COMMENTS) > 80_000
    probe = tmp_path / "probe.nrrd"
    probe.write_bytes(hostile)
    assert sitk.ReadImage(str(probe)).GetSize() == (8, 8, 8)          # the hole is real for a plain reader
    existing = refuse(tmp_path, hostile, "long.nrrd")
    missing = refuse(tmp_path, nrrd(str(secret.with_name("absent.raw")).encode()), "long.nrrd")
    assert "detached" in existing and existing == missing              # tells nothing about the server's files


@pytest.mark.parametrize("field", [b"data file", b"datafile", b"DATA FILE", b"Data  File"])
def test_every_spelling_of_the_nrrd_field_is_refused(tmp_path: Path, secret: Path, field: bytes) -> None:
    assert "detached" in refuse(tmp_path, nrrd(str(secret).encode(), b"", field), "x.nrrd")


@pytest.mark.parametrize("end", [b"\r", b"\r\n"])
def test_an_nrrd_data_file_after_a_bare_carriage_return_is_refused(tmp_path: Path, secret: Path, end: bytes) -> None:
    """NRRD's reader ends a line at a bare \\r: a field hidden after one in a \\n-ended line is a field."""
    hostile = (b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 8 8 8\nencoding: raw" + end + b"data file: "
               + str(secret).encode() + b"\n\n")
    probe = tmp_path / "probe.nrrd"
    probe.write_bytes(hostile)
    assert sitk.ReadImage(str(probe)).GetSize() == (8, 8, 8)          # the hole is real for a plain reader
    assert "detached" in refuse(tmp_path, hostile, "cr.nrrd")


def test_a_compressed_mha_is_read_and_a_corrupt_one_refused_not_filled_from_memory(tmp_path: Path) -> None:
    """ITK's reader leaves the voxels of a stream that fails to inflate as its memory held them."""
    data = np.random.default_rng(3).random((8, 9, 10)).astype(np.float32)
    path = tmp_path / "c.mha"
    sitk.WriteImage(sitk.GetImageFromArray(data), str(path), True)      # compressed
    assert b"CompressedData = True" in path.read_bytes()[:500]
    np.testing.assert_array_equal(read_upload(path, "c.mha").array, data.transpose(2, 1, 0))
    raw = path.read_bytes()
    start = raw.index(b"ElementDataFile = LOCAL\n") + len(b"ElementDataFile = LOCAL\n")
    header = raw[:start]
    for body, name in ((b"x" * 100, "garbage.mha"), (raw[start:-50], "cut.mha"), (b"", "empty.mha")):
        assert "do not inflate" in refuse(tmp_path, header + body, name)
    assert "carriage return" in refuse(tmp_path, header.replace(b"NDims = 3", b"NDims = 3\rOffset = 1 2 3"), "cr.mha")


def test_an_mha_without_its_element_data_file_line_is_named_so(tmp_path: Path) -> None:
    """Its voxel data are read as header lines: the answer says what is missing, not what the
    data's bytes look like."""
    data = np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes()
    header = b"ObjectType = Image\nNDims = 3\nDimSize = 10 10 10\nElementType = MET_FLOAT\n"
    assert "no ElementDataFile line" in refuse(tmp_path, header + data, "n.mha")


def test_a_compressed_mha_that_declares_more_than_the_limit_is_413_before_it_inflates(tmp_path: Path) -> None:
    """As every other decoder's bomb: too large (413, naming the file), not an unsupported file."""
    header = (b"ObjectType = Image\nNDims = 3\nDimSize = 2000 2000 30\nElementType = MET_FLOAT\n"
              b"CompressedData = True\nElementDataFile = LOCAL\n")
    path = tmp_path / "b.mha"
    path.write_bytes(header + b"x\x9c" + b"\0" * 100)
    with pytest.raises(PayloadTooLarge, match="b.mha: its header declares .* bytes of voxel data .* more than"):
        read_upload(path, "b.mha", max_decoded_bytes=128 << 20)


@pytest.mark.parametrize("value", [b"LIST", b"slice%03d.raw 1 8 1", b"/etc/passwd"])
def test_nrrd_list_and_pattern_forms_are_refused(tmp_path: Path, value: bytes) -> None:
    assert "detached" in refuse(tmp_path, nrrd(value, b""), "x.nrrd")


@pytest.mark.parametrize("comments", [b"", b"Comment = x\n" * 3000])
@pytest.mark.parametrize("key", [b"ElementDataFile", b"elementdatafile"])
def test_an_mha_element_data_file_is_refused(tmp_path: Path, secret: Path, comments: bytes, key: bytes) -> None:
    existing = refuse(tmp_path, mha(str(secret).encode(), comments, key), "x.mha")
    assert "detached" in existing
    assert existing == refuse(tmp_path, mha(b"/no/such/file.raw", comments, key), "x.mha")
    assert "detached" in refuse(tmp_path, mha(b"LIST", comments, key), "x.mha")


def test_a_header_too_long_to_end_is_refused(tmp_path: Path) -> None:
    endless = b"NRRD0004\n" + b"# x\n" * (MAX_HEADER_BYTES // 4 + 10)
    assert "longer than" in refuse(tmp_path, endless, "endless.nrrd")


def test_attached_data_after_a_long_header_still_read(tmp_path: Path) -> None:
    """Comments and unknown fields are dropped; the geometry and the voxels are kept."""
    data = np.arange(8 * 8 * 8, dtype=np.uint8)
    content = (b"NRRD0004\n" + COMMENTS + b"type: uchar\ndimension: 3\nsizes: 8 8 8\nencoding: raw\n"
               b"space: left-posterior-superior\nspace directions: (2,0,0) (0,2,0) (0,0,3)\n"
               b"space origin: (1,2,3)\nmystery field: 7\nowner:=Doe^Jane\n\n" + data.tobytes())
    path = tmp_path / "ok.bin"
    path.write_bytes(content)
    vol = read_upload(path, "ok.nrrd")
    np.testing.assert_array_equal(vol.array, data.reshape(8, 8, 8).transpose(2, 1, 0).astype(np.float32))
    np.testing.assert_allclose(vol.spacing, [2, 2, 3])
    np.testing.assert_allclose(vol.affine[:3, 3], [-1, -2, 3])          # LPS origin -> RAS


def test_a_two_file_nifti_header_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "v.nii"
    sitk.WriteImage(sitk.GetImageFromArray(np.ones((4, 5, 6), np.float32)), str(path))
    raw = bytearray(path.read_bytes())
    raw[344:348] = b"ni1\x00"                         # "my voxels are in the .img beside me"
    assert "pair" in refuse(tmp_path, bytes(raw[:352]), "x.hdr")


MHA_HEAD = b"ObjectType = Image\nNDims = 3\nDimSize = 8 8 8\nElementType = MET_UCHAR\n"


PAYLOAD = bytes(77_000)


@pytest.mark.parametrize("name, content, words", [
    # ITK's NRRD reader crashes the process on these dimensions; MetaIO loops for ever on these NDims.
    ("d12.nrrd", b"NRRD0004\ntype: uchar\ndimension: 12\nsizes: " + b"2 " * 12 + b"\nspacings: " + b"1 " * 12
     + b"\nencoding: raw\n\n", "dimension is not a whole number of 1 to 4 axes"),
    ("minus.mha", b"ObjectType = Image\nNDims = -1\nDimSize = 8 8 8\nElementSpacing = 1 1 1\nElementType = MET_UCHAR\n"
     b"ElementDataFile = LOCAL\n", "NDims is not a whole number of 1 to 4 axes"),
    ("huge.mha", b"ObjectType = Image\nNDims = 2147483647\nDimSize = 8 8 8\nElementType = MET_UCHAR\n"
     b"ElementDataFile = LOCAL\n", "NDims is not"),
    # A size past 32 bits, which ITK counts as 1 and teem allocates whole.
    ("wrap.nrrd", b"NRRD0004\ntype: float\ndimension: 3\nsizes: 4294967297 1 1\nspacings: 1 1 1\nencoding: raw\n\n",
     "sizes does not give 3 whole numbers"),
    # Inflated and thrown away, uncounted.
    ("skip.nrrd", b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 8 8 8\nspacings: 1 1 1\nencoding: gzip\n"
     b"byte skip: 2000000000\n\n", "byte skip is not 0 for compressed data"),
    # MetaIO takes 1 or T for compressed, fails to inflate and returns its buffer unfilled (an earlier
    # upload's): read as compressed here too, by the bounded inflater.
    ("one.mha", b"ObjectType = Image\nNDims = 3\nDimSize = 8 8 8\nElementSpacing = 1 1 1\nElementType = MET_UCHAR\n"
     b"CompressedData = 1\nElementDataFile = LOCAL\n", "do not inflate"),
    ("text.mha", b"ObjectType = Image\nNDims = 3\nDimSize = 8 8 8\nElementSpacing = 1 1 1\nElementType = MET_STRING\n"
     b"ElementDataFile = LOCAL\n", "ElementType is not a number type"),
    ("bz.nrrd", b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 8 8 8\nspacings: 1 1 1\nencoding: bzip2\n\n",
     "encoding 'bzip2' is not one this reader knows"),
])
def test_a_header_its_reader_would_crash_hang_or_misread_on_is_refused_first(tmp_path: Path, name: str,
                                                                             content: bytes, words: str) -> None:
    assert words in refuse(tmp_path, content + PAYLOAD, name)


def test_metaimage_yes_no_values_are_read_as_metaio_reads_them(tmp_path: Path) -> None:
    """``T`` or ``1`` is yes, ``0`` no: files other tools write so are read, a compressed one inflated here."""
    array = np.arange(4 * 5 * 6, dtype=np.int16).reshape(6, 5, 4)
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((1.0, 1.0, 3.0))
    sitk.WriteImage(image, str(tmp_path / "z.mha"), useCompression=True)
    content = (tmp_path / "z.mha").read_bytes()
    assert b"CompressedData = True" in content and b"BinaryData = True" in content
    written = (content.replace(b"CompressedData = True", b"CompressedData = T")
               .replace(b"BinaryData = True", b"BinaryData = 1")
               .replace(b"BinaryDataByteOrderMSB = False", b"BinaryDataByteOrderMSB = 0"))
    upload = tmp_path / "upload.bin"
    upload.write_bytes(written)
    read = read_upload(upload, "z.mha")
    np.testing.assert_array_equal(read.array, array.transpose(2, 1, 0).astype(read.array.dtype))


def test_an_mha_header_size_that_skips_into_the_rebuilt_header_is_refused(tmp_path: Path) -> None:
    """The data follow the rebuilt header: a HeaderSize of 5 read the header's own text as voxels."""
    head = MHA_HEAD + b"ElementSpacing = 1 1 3\n"
    assert "HeaderSize" in refuse(tmp_path, head + b"HeaderSize = 5\nElementDataFile = LOCAL\n" + bytes(512), "h.mha")
    upload = tmp_path / "ok.mha"
    upload.write_bytes(head + b"HeaderSize = -1\nElementDataFile = LOCAL\n" + bytes(range(256)) * 2)
    assert read_upload(upload, "ok.mha").array.max() == 255


def test_an_mha_with_latin1_metadata_and_one_of_gzip_data_are_read_as_itk_reads_them(tmp_path: Path) -> None:
    """ITK writes metadata fields in the file's own script (a name, a comment) and reads data
    compressed as zlib or gzip: such files are read; a field the service reads that is not ASCII is
    refused by name (its value would be guessed)."""
    import gzip

    data = np.random.default_rng(5).random((8, 9, 10)).astype(np.float32)
    path = tmp_path / "c.mha"
    sitk.WriteImage(sitk.GetImageFromArray(data), str(path))
    raw = path.read_bytes()
    with_name = raw.replace(b"ElementType", "PatientComment = Müller Zoë\nElementType".encode("latin-1"), 1)
    path.write_bytes(with_name)
    assert sitk.GetArrayFromImage(sitk.ReadImage(str(path))).shape == data.shape        # ITK reads it
    np.testing.assert_array_equal(read_upload(path, "c.mha").array, data.transpose(2, 1, 0))
    start = raw.index(b"ElementDataFile = LOCAL\n") + len(b"ElementDataFile = LOCAL\n")
    packed = gzip.compress(raw[start:])
    header = raw[:start].replace(b"CompressedData = False", b"CompressedData = True\nCompressedDataSize = %d" % len(packed))
    path.write_bytes(header + packed)
    assert np.allclose(sitk.GetArrayFromImage(sitk.ReadImage(str(path))), data)         # ITK reads gzip too
    np.testing.assert_array_equal(read_upload(path, "c.mha").array, data.transpose(2, 1, 0))
    spaced = raw.replace(b"ElementSpacing = 1 1 1", "ElementSpacing = 1 1 1\u00a0".encode("utf-8"), 1)
    assert b"\xc2\xa0" in spaced
    assert "ElementSpacing" in refuse(tmp_path, spaced, "s.mha") and "not ASCII" in refuse(tmp_path, spaced, "s.mha")
