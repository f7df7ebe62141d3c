"""What a stream session is asked for (its options) and what it may hold (its limits).

Example:
    >>> SessionOptions.from_message({"type": "start", "mc_samples": 20}, "start").mc_samples
    20
    >>> StreamLimits().max_slices
    2000
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from service.core.client_json import client_json
from service.core.errors import InvalidParameter
from service.core.settings import Settings

MAX_MC_SAMPLES = 1000


@dataclass(frozen=True)
class StreamLimits:
    """What one session may hold."""

    max_slices: int = 2000
    max_pixels: int = 1024 * 1024
    max_bytes: int = 512 * 2**20
    """What a session may keep in memory: its slices' pixels as float32, each slice's preparation and each ended
    stack's, reserved as its slices come (five to six times the pixels)."""
    max_stack_slices: int = 128
    """What one stack may hold (``max_slices_per_stack``, as an upload: its stage's work grows with the cube)."""
    max_stacks: int = 32
    """What one session may hold (``max_files``, as a request): each stack's end refits the session's
    ended stacks with it, so its cost grows with the stacks before it."""

    @classmethod
    def of(cls, settings: Settings) -> "StreamLimits":
        """The limits the ``stream_*`` settings give (``/v1/stream`` and ``svrnet-mrd`` alike)."""
        return cls(settings.stream_max_slices, settings.stream_max_pixels, int(settings.stream_max_session_mb * 2**20),
                   settings.max_slices_per_stack, settings.max_files)


@dataclass(frozen=True)
class SessionOptions:
    """A session's options, as ``/v1/predict``'s form and Stream v1's ``start`` name them.

    Example:
        >>> SessionOptions.from_message({"type": "start", "mc_samples": 20}, "start").mc_samples
        20
        >>> SessionOptions.from_json('{"mc_samples": 0}', "config")
        Traceback (most recent call last):
        ...
        service.core.errors.InvalidParameter: config.mc_samples: an integer from 1 to 1000 is required
    """

    model: str = "default"
    mc_samples: int = 100
    variance_threshold: float | None = None
    max_expected_error_mm: float | None = None
    bias_correction: bool = True
    masks_hold_csf: bool = False
    """The mask frames are the skull's inside (brain and extra-axial CSF), as ``/v1/predict``'s form field."""

    @classmethod
    def from_json(cls, text: str, where: str) -> "SessionOptions":
        """Options from a JSON object holding nothing else (an MRD config text); :class:`InvalidParameter`
        names the field at fault, ``where`` the message."""
        try:
            given = client_json(text)
        except ValueError:
            raise InvalidParameter(f"{where}: not a JSON object") from None
        if not isinstance(given, dict):
            raise InvalidParameter(f"{where}: not a JSON object")
        return cls.from_fields(given, where)

    @classmethod
    def from_start(cls, message: dict) -> "SessionOptions":
        """Options from a stream's ``start`` message, which holds nothing but its type and them: a
        misspelt option is named, as ``/v1/predict`` names an unknown form field, not left at its default.

        Example:
            >>> SessionOptions.from_start({"type": "start", "variance_treshold": 40})
            Traceback (most recent call last):
            ...
            service.core.errors.InvalidParameter: start: unknown options ['variance_treshold']
        """
        return cls.from_fields(message, "start", {"type"})

    @classmethod
    def from_fields(cls, given: dict, where: str, other: set[str] = frozenset()) -> "SessionOptions":
        """:meth:`from_message` of ``given``, which may hold nothing but the options and ``other``."""
        unknown = sorted(set(given) - set(other) - set(cls.__dataclass_fields__))
        if unknown:
            raise InvalidParameter(f"{where}: unknown options {unknown}")
        return cls.from_message(given, where)

    @classmethod
    def from_message(cls, given: dict, where: str) -> "SessionOptions":
        """Options from the fields of a message (others are left to the caller)."""
        model, samples = given.get("model", "default"), given.get("mc_samples", 100)
        if not isinstance(model, str) or not 1 <= len(model) <= 128:
            raise InvalidParameter(f"{where}.model: a model name (string) is required")
        if isinstance(samples, bool) or not isinstance(samples, int) or not 1 <= samples <= MAX_MC_SAMPLES:
            raise InvalidParameter(f"{where}.mc_samples: an integer from 1 to {MAX_MC_SAMPLES} is required")
        limits = {}
        for name in ("variance_threshold", "max_expected_error_mm"):
            value = given.get(name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                      or not math.isfinite(value) or not value > 0):
                raise InvalidParameter(f"{where}.{name}: a positive number (or null) is required")
            limits[name] = None if value is None else float(value)
        flags = {name: given.get(name, default) for name, default in (("bias_correction", True), ("masks_hold_csf", False))}
        for name, value in flags.items():
            if not isinstance(value, bool):
                raise InvalidParameter(f"{where}.{name}: true or false")
        return cls(model, samples, **limits, **flags)
