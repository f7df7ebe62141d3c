"""The order a DICOM series' slices were acquired in, from their acquisition times.

Fetal stacks are 2D multi-slice acquisitions, usually interleaved; the scanner writes each slice's
acquisition time. The stack-consistency stage follows the fetus's motion over that order
(:mod:`service.consistency.slice_order`), so the reader keeps it: only the ranks, never the times
(a time of day is an identifying attribute in DICOM's de-identification profiles).

An order is kept only when every slice has a time and no two share one (vendors that stamp the
series' start on every slice, or simultaneous multi-band slices, say nothing about the order).

Example:
    >>> from pydicom.dataset import Dataset
    >>> slices = [Dataset() for _ in range(4)]
    >>> for ds, t in zip(slices, ["101500.00", "101502.10", "101501.05", "101503.15"]):
    ...     ds.AcquisitionTime = t
    >>> order_of([seconds(ds) for ds in slices])
    (0, 2, 1, 3)
"""

from __future__ import annotations

import re

import numpy as np

MIN_GAP_S = 1e-3
"""Times closer than this are the same time (no order between those slices)."""
MAX_SPAN_S = 6 * 3600.0
"""A stack takes minutes: times spread over more than this are not one acquisition's (or wrapped at midnight)."""
_TIME = re.compile(r"^(\d{2}):?(\d{2})?:?(\d{2})?(\.\d+)?$")


def parse_time(text: object) -> float | None:
    """Seconds since midnight of a DICOM TM (``HHMMSS.FFFFFF``, ``HH:MM:SS`` of ACR-NEMA) or of the
    time part of a DT (``YYYYMMDDHHMMSS.FFFFFF&ZZXX``, its date ignored); ``None`` if unreadable.

    Example:
        >>> parse_time("101502.5"), parse_time("20261124101502.5+0100"), parse_time("xx")
        (36902.5, 36902.5, None)
    """
    s = str(text or "").strip()
    if len(s) >= 14 and s[:8].isdigit():          # a DT: drop the date and the UTC offset
        s = re.split(r"[+-]", s[8:])[0]
    m = _TIME.match(s)
    if not m:
        return None
    hh, mm, ss, frac = m.groups()
    value = int(hh) * 3600 + int(mm or 0) * 60 + int(ss or 0) + float(frac or 0.0)
    return value if value < 86400 else None


def seconds(ds, frame_content=None) -> float | None:  # noqa: ANN001 - pydicom datasets
    """A slice's acquisition time (seconds since midnight): ``frame_content``'s
    ``FrameAcquisitionDateTime`` for a frame of an Enhanced multi-frame image, else the dataset's
    ``AcquisitionDateTime`` or ``AcquisitionTime``."""
    for source, key in ((frame_content, "FrameAcquisitionDateTime"), (ds, "AcquisitionDateTime"),
                        (ds, "AcquisitionTime")):
        if source is not None and key in source:
            value = parse_time(source[key].value)
            if value is not None:
                return value
    return None


def order_of(times: list[float | None]) -> tuple[int, ...] | None:
    """The slice indices in acquisition order, or ``None`` when the times do not tell it."""
    if len(times) < 2 or any(t is None for t in times):
        return None
    t = np.asarray(times, dtype=np.float64)
    if np.ptp(t) > MAX_SPAN_S or (np.diff(np.sort(t)) < MIN_GAP_S).any():
        return None
    return tuple(int(k) for k in np.argsort(t, kind="stable"))
