"""A header whose geometry its reader would make up is refused, naming the file and the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.core.errors import UnsupportedFile, UnusableImage
from service.io.header_geometry import geometry_problem
from service.io.readers import read_upload

NRRD_HEAD = b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 8 8 8\nencoding: raw\n"
MHA_HEAD = b"ObjectType = Image\nNDims = 3\nDimSize = 8 8 8\nElementType = MET_UCHAR\n"


@pytest.mark.parametrize(("name", "content", "words"), [
    ("g.nrrd", NRRD_HEAD + b"\n", "gives no voxel size (no space directions or spacings)"),
    ("g.nrrd", NRRD_HEAD + b"spacings: nan nan nan\n\n", "spacings holds values that are not finite"),
    ("g.nrrd", NRRD_HEAD + b"space: left-posterior-superior\nspace directions: (1,0,0) (0.5,1,0) (0,0,3)\n\n",
     "sheared"),
    ("g.mha", MHA_HEAD + b"ElementDataFile = LOCAL\n", "gives no voxel size (no elementspacing or elementsize)"),
    ("g.mha", MHA_HEAD + b"ElementSpacing = 1 1 3\nOffset = nan 0 0\nElementDataFile = LOCAL\n",
     "offset holds values that are not finite"),
    ("g.mha", MHA_HEAD + b"ElementSpacing = 1 1 -3\nElementDataFile = LOCAL\n", "not positive"),
    ("g.mha", MHA_HEAD + b"ElementSpacing = 1 1 3\nOffset = a b c\nElementDataFile = LOCAL\n", "offset is not 3 numbers"),
    ("g.nrrd", NRRD_HEAD + b"space: left-posterior-superior\nspace directions: (1e200,0,0) (0,1,0) (0,0,1)\n\n",
     "beyond 1e+06 mm"),                                              # the reader would put 1 mm in its place
    ("g.nrrd", NRRD_HEAD + b"spacings: 1 1 3\n\n", "names no anatomical space"),    # ITK would say LPS
    ("g.nrrd", NRRD_HEAD + b"space: scanner-xyz\nspace directions: (1,0,0) (0,1,0) (0,0,3)\n\n", "'scanner-xyz'"),
    ("g.nrrd", NRRD_HEAD + b"space: 3D-right-handed\nspace directions: (1,0,0) (0,1,0) (0,0,3)\n\n",
     "names no anatomical space"),
    ("g.nrrd", NRRD_HEAD + b"space dimension: 3\nspace directions: (1,0,0) (0,1,0) (0,0,3)\n\n",
     "names no anatomical space"),
    # ITK places every space with time as LPS: RAST would be turned, LAST mirrored
    ("g.nrrd", NRRD_HEAD.replace(b"8 8 8", b"8 8 8 1").replace(b"dimension: 3", b"dimension: 4")
     + b"space: RAST\nspace directions: (1,0,0,0) (0,1,0,0) (0,0,3,0) none\n\n", "'rast' is a space with time"),
    ("g.nrrd", NRRD_HEAD.replace(b"8 8 8", b"8 8 8 1").replace(b"dimension: 3", b"dimension: 4")
     + b"space: left-anterior-superior-time\nspace directions: (1,0,0,0) (0,1,0,0) (0,0,3,0) none\n\n",
     "'left-anterior-superior-time' is a space with time"),
])
def test_a_geometry_the_reader_would_make_up_is_422(tmp_path: Path, name: str, content: bytes, words: str) -> None:
    """As a NIfTI header without voxel sizes, with a sheared sform or without any orientation is: never
    1 mm or 0 invented, nor which side is left."""
    upload = tmp_path / name
    upload.write_bytes(content + bytes(512))
    with pytest.raises(UnusableImage) as info:
        read_upload(upload, name)
    assert name in info.value.detail and words in info.value.detail, info.value.detail



@pytest.mark.parametrize("field", [b"Offset = 10", b"Offset = 1 2", b"ElementSpacing = 1 1 3\nPosition = 0 x 0",
                                   b"TransformMatrix = 1 0 0 0 1 0"])
def test_an_mha_placement_of_too_few_numbers_is_refused_not_filled_with_zeros(tmp_path: Path, field: bytes) -> None:
    upload = tmp_path / "p.mha"
    spacing = b"" if b"ElementSpacing" in field else b"ElementSpacing = 1 1 3\n"
    upload.write_bytes(MHA_HEAD + spacing + field + b"\nElementDataFile = LOCAL\n" + bytes(512))
    with pytest.raises((UnusableImage, UnsupportedFile)) as info:
        read_upload(upload, "p.mha")
    assert "p.mha" in info.value.detail


def test_a_header_rebuilt_with_every_field_in_place_has_no_problem() -> None:
    """The checks refuse what is missing or wrong, not what is written otherwise (other fields, spellings)."""
    assert geometry_problem(b"NRRD0004\nspace: right-anterior-superior\nspace directions: (1,0,0) (0,1,0) (0,0,3)"
                            b"\nspace origin: (-10,5,2.5e1)\n\n", "nrrd") is None
    assert geometry_problem(b"ElementSpacing = 1 1 3\nNDims = 3\nOffset = 1 2 3\n"
                            b"TransformMatrix = 1 0 0 0 1 0 0 0 1\n", "mha") is None
