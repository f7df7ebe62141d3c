"""Names that come from clients (file names, ZIP member names), made safe to echo in any answer.

Control and format characters -- C0/C1 controls, bidirectional overrides such as U+202E, zero-width
characters, line and paragraph separators -- are removed, surrounding white space is trimmed and the
name is cut to :data:`MAX_NAME` characters, so an answer or a log line can never be rewritten or
disguised by a name.

Example:
    >>> clean_name("scan\\u202egpj.nii.gz\\r\\nX-Evil: 1")
    'scangpj.nii.gzX-Evil: 1'
    >>> clean_name("dir/sub\\\\IM0001")
    'dir/sub\\\\IM0001'
"""

from __future__ import annotations

import re
import unicodedata

MAX_NAME = 255
IMAGE_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd", ".dcm", ".zip", ".gz")


UNSAFE_CATEGORIES = ("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp")
"""Unicode categories never echoed: controls, format characters, surrogates, private and unassigned
code points, line and paragraph separators."""


def clean_name(name: str) -> str:
    """``name`` without control/format/separator characters, trimmed, at most :data:`MAX_NAME` long."""
    kept = "".join(c for c in name if unicodedata.category(c) not in UNSAFE_CATEGORIES)
    return kept.strip()[:MAX_NAME]


def shown_name(name: str) -> str:
    """``name`` as a message shows a client's field or parameter name: as it is where it is clean, else
    quoted with its hidden characters escaped (``'stack\\x00'``), so that the message names what was
    sent, not the clean name it was mistaken for.

    Example:
        >>> shown_name("stak"), shown_name("stack\\x00"), shown_name("model ")
        ('stak', "'stack\\\\x00'", "'model '")
    """
    if clean_name(name) == name and name:
        return name
    return ascii(name[:MAX_NAME])


def has_unsafe_characters(name: str) -> bool:
    """Whether ``name`` holds a character :func:`clean_name` would remove (not counting white space
    at its ends).

    Example:
        >>> has_unsafe_characters("axial 1"), has_unsafe_characters("ax\u202eial")
        (False, True)
    """
    return any(unicodedata.category(c) in UNSAFE_CATEGORIES for c in name)


def unique_stems(names: list[str], max_length: int | None = None) -> list[str]:
    """File-system-safe stems of upload names (extensions dropped, only ``[A-Za-z0-9._-]``, none
    starting with ``-`` (which a shell's tools take for an option) or ``.`` (a hidden file), at most
    ``max_length`` characters), made unique with ``-1``, ``-2`` ... in order, regardless of case: on
    macOS and Windows ``AX`` and ``ax`` are one file, and one unzipped over the other would be lost.

    Example:
        >>> unique_stems(["axial.nii.gz", "axial.nii", "../x y.mha", "stacks[3]", "AXIAL.nii", "-rf.nii", "-.x.nii"])
        ['axial', 'axial-1', 'x_y', 'stacks_3', 'AXIAL-2', 'rf', 'x']
        >>> unique_stems(["abcdef.nii", "abcdeg.nii"], max_length=4)
        ['abcd', 'ab-1']
    """
    out: list[str] = []
    for name in names:
        base = name.replace("\\", "/").rsplit("/", 1)[-1]
        for suffix in IMAGE_SUFFIXES:
            if base.lower().endswith(suffix):
                base = base[: -len(suffix)]
                break
        stem = (re.sub(r"[^A-Za-z0-9._-]+", "_", base).lstrip("-._").rstrip("._") or "stack")[:max_length]
        candidate, k = stem, 0
        while candidate.lower() in {o.lower() for o in out}:
            k += 1
            candidate = f"{stem[:None if max_length is None else max_length - len(str(k)) - 1]}-{k}"
        out.append(candidate)
    return out


__all__ = ["MAX_NAME", "clean_name", "unique_stems"]
