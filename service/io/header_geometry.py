"""The geometry of a rebuilt NRRD or MetaImage header, checked before a reader places the voxels.

ITK's readers make up what a header leaves out or gets wrong: 1 mm for a missing or non-finite
voxel size, 0 for an origin they cannot read, LPS for a space that names no side of the patient. A
made-up geometry places the stack, and with it every slice's mirror twin, somewhere the scanner did
not, so :func:`geometry_problem` names such a header and the upload is refused (415) rather than
posed. The header is the one :func:`~service.io.headers.clean_header` rebuilt from allowed fields.

Example:
    >>> geometry_problem(b"NRRD0004\\nspace: LPS\\nspacings: 1 1 3\\n\\n", "nrrd") is None
    True
"""

from __future__ import annotations

import re

from service.io.headers import header_fields

_NOT_FINITE = re.compile(rb"nan|inf", re.I)
MAX_GEOMETRY_MM = 1e6
"""Larger numbers in a header's sizes, directions or origin are no scanner's (the reader would put
1 mm in place of a direction it cannot normalise)."""
_NUMBER = re.compile(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
SIZE_FIELDS = {"nrrd": ("spacedirections", "spacings"), "mha": ("elementspacing", "elementsize")}
PLACE_FIELDS = {"nrrd": ("spaceorigin",), "mha": ("offset", "position", "origin", "transformmatrix", "rotation",
                                                   "orientation")}


_MHA_MATRICES = ("transformmatrix", "rotation", "orientation")


def _mha_counts(fields: dict[str, bytes]) -> str | None:
    """Why an MHA header's sizes, origin or axes are not ``NDims`` plain numbers (axes: ``NDims``
    squared), or None: its reader reads what numbers it finds and puts 0 in place of the rest.

    Example:
        >>> _mha_counts({"ndims": b" 3", "offset": b" 10"})
        "its MHA header's offset is not 3 numbers"
        >>> _mha_counts({"ndims": b" 3", "offset": b" 1 2 3", "transformmatrix": b" 1 0 0 0 1 0 0 0 1"}) is None
        True
    """
    ndims = fields.get("ndims", b"").strip()
    if not ndims.isdigit():
        return None                                      # the reader refuses the header itself
    n = int(ndims)
    for name in (*SIZE_FIELDS["mha"], *PLACE_FIELDS["mha"]):
        if name in fields:
            want = n * n if name in _MHA_MATRICES else n
            values = fields[name].split()
            if len(values) != want or not all(_NUMBER.fullmatch(v) for v in values):
                return f"its MHA header's {name} is not {want} numbers"
    return None


ANATOMICAL_SPACES = frozenset(("right-anterior-superior", "left-anterior-superior", "left-posterior-superior",
                               "ras", "las", "lps"))
"""NRRD ``space`` values that say which side is the patient's left (teem's names, long and short;
lower case). ``scanner-xyz`` and ``3D-right-handed`` do not: ITK reads them as LPS whatever the
file meant."""
TIMED_SPACES = frozenset(f"{name}{time}" for name in ANATOMICAL_SPACES for time in ("-time", "t"))
"""The anatomical spaces' time variants (``RAST``, ``left-anterior-superior-time``, ...): ITK places
every one of them as LPS, so that a ``RAST`` stack would be turned half a turn and a ``LAST`` one
mirrored; they are refused by name."""


def geometry_problem(header: bytes, kind: str) -> str | None:
    """Why a rebuilt header's geometry would be made up by its reader, or None: no voxel size at all
    (the reader invents 1 mm, as for a NIfTI header without one), or sizes, origin or axes that are
    not finite numbers (the reader puts 1 mm or 0 in their place) or, in an MHA header, not as many
    numbers as the image has dimensions (:func:`_mha_counts`), or a size that is not positive; or an
    NRRD header that names no anatomical ``space`` (:data:`ANATOMICAL_SPACES`): which side is the
    patient's left is then unknown, and it decides each slice's mirror twin, as a NIfTI header with
    neither transform is refused for.

    Example:
        >>> geometry_problem(b"NRRD0004\\ntype: uchar\\nsizes: 2 2 2\\n\\n", "nrrd")
        'its NRRD header gives no voxel size (no space directions or spacings); the reader would invent 1 mm'
        >>> geometry_problem(b"NRRD0004\\nspace: RAS\\nspace directions: (1,0,0) (0,1,0) (0,0,3)\\n\\n", "nrrd") is None
        True
        >>> geometry_problem(b"NRRD0004\\nspacings: 1 1 3\\nspace origin: (0,0,0)\\n\\n", "nrrd")[:45]
        'its NRRD header names no anatomical space (sp'
        >>> geometry_problem(b"NRRD0004\\nspace: scanner-xyz\\nspace directions: (1,0,0) (0,1,0) (0,0,3)\\n\\n", "nrrd")[-39:]
        "space 'scanner-xyz' names no such thing"
        >>> geometry_problem(b"NRRD0004\\nspace: LAST\\nspace directions: (1,0,0,0) (0,1,0,0) (0,0,3,0)\\n\\n", "nrrd")[:52]
        "its NRRD header's space 'last' is a space with time,"
        >>> geometry_problem(b"NRRD0004\\nspace directions: (1e200,0,0) (0,1,0) (0,0,1)\\n\\n", "nrrd")[-9:]
        '1e+06 mm)'
    """
    fields = header_fields(header, kind)
    sizes = [fields[name] for name in SIZE_FIELDS[kind] if name in fields]
    if not sizes:
        names = " or ".join(n.replace("space", "space ") if kind == "nrrd" else n for n in SIZE_FIELDS[kind])
        return (f"its {kind.upper()} header gives no voxel size (no {names}); the reader would invent 1 mm")
    for name in (*SIZE_FIELDS[kind], *PLACE_FIELDS[kind]):
        if name in fields and (_NOT_FINITE.search(fields[name]) or
                               any(abs(float(v)) > MAX_GEOMETRY_MM for v in _NUMBER.findall(fields[name]))):
            return (f"its {kind.upper()} header's {name} holds values that are not finite numbers (or beyond "
                    f"{MAX_GEOMETRY_MM:.0e} mm)")
    if kind == "mha" and (problem := _mha_counts(fields)) is not None:
        return problem
    if any(float(v) <= 0 for v in _NUMBER.findall(fields.get("spacings", b"") + fields.get("elementspacing", b"")
                                                 + fields.get("elementsize", b""))):
        return f"its {kind.upper()} header gives a voxel size that is not positive"
    directions = fields.get("spacedirections", b"") if kind == "nrrd" else b""
    if b"none" in directions.lower() and (placed := directions.count(b"(")) < 3:
        return (f"its NRRD header's space directions place {placed} of the image's axes (the others 'none'); the "
                "reader would invent 1 mm for the rest")
    space = fields.get("space", b"").strip().decode("latin-1").lower()
    if kind == "nrrd" and space in TIMED_SPACES:
        return (f"its NRRD header's space {space!r} is a space with time, which the reader would place as LPS "
                "(a RAS or LAS stack turned or mirrored): write the stack in its 3D space (RAS, LAS or LPS)")
    if kind == "nrrd" and space not in ANATOMICAL_SPACES:
        return ("its NRRD header names no anatomical space (space: RAS, LAS or LPS): which side is the patient's left "
                "is unknown, and it decides each slice's mirror twin" + (f"; space {space!r} names no such thing"
                                                                           if space else ""))
    return None

__all__ = ["ANATOMICAL_SPACES", "MAX_GEOMETRY_MM", "TIMED_SPACES", "geometry_problem"]
