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

import unicodedata

MAX_NAME = 255


def clean_name(name: str) -> str:
    """``name`` without control/format/separator characters, trimmed, at most :data:`MAX_NAME` long."""
    kept = "".join(c for c in name if unicodedata.category(c) not in ("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"))
    return kept.strip()[:MAX_NAME]


__all__ = ["MAX_NAME", "clean_name"]
