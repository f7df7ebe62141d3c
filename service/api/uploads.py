"""Uploaded files: spooled into a private temporary directory, read, and deleted with it."""

from __future__ import annotations

import functools
import logging
import re
import shutil
import tempfile
import threading
import time
import typing
from collections import Counter
from collections.abc import Awaitable, Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

from fastapi import Depends, File, Form, Request, UploadFile, params
from pydantic import AfterValidator, StringConstraints, WithJsonSchema

from service.api.deps import SettingsDep
from service.consistency.slice_order import MAX_TEXT, PATTERN, VALUES, SliceOrder, per_stack
from service.core.cancellation import carried, checkpoint
from service.core.errors import InvalidParameter, NotReady, UnusableImage
from service.core.names import clean_name, shown_name
from service.core.settings import Settings
from service.pipeline.stack_upload import StackUpload, mask_on_stack_grid
from service.io.limits import DecodeBudget, folders_take_writes, raise_if_out_of_space
from service.io.readers import MAX_DECODED_BYTES, read_upload
from service.preprocess.stack import slice_axis_of

log = logging.getLogger(__name__)

READ_WORKERS = 2
# Files decoded at once in the whole process, whatever the number of requests: with the per-file
# limit this bounds the memory that decoding can take (a request waits for its turn here).
DECODING = threading.BoundedSemaphore(READ_WORKERS)


STALE_PREFIXES = ("svrnet-req-", "svrnet-read-", "svrnet-zip-")
"""The temporary folders of requests and readers (:func:`upload_directory`, :mod:`service.io.readers`)."""


SCRATCH_NOT_WRITABLE = "the server cannot write its scratch folder (SVRNET_TMP_DIR); retry later"


@contextmanager
def upload_directory(base: Path | None) -> Iterator[Path]:
    """A private directory for this request's files, removed afterwards whatever happens; the readers
    decode into it too, so that a process killed mid-request leaves one folder for
    :func:`sweep_stale_uploads`. A scratch folder the server may not write is the server's fault, not
    the request's: 503 (:func:`scratch_takes_uploads` has ``/readyz`` say so too); a full one 507."""
    try:
        scratch = tempfile.TemporaryDirectory(prefix="svrnet-req-", dir=base)
    except OSError as exc:
        raise_if_out_of_space(exc)
        log.error("the scratch folder cannot be written (%s)", type(exc).__name__)
        raise NotReady(SCRATCH_NOT_WRITABLE) from exc
    with scratch as tmp:
        yield Path(tmp)


def scratch_takes_uploads(base: Path | None) -> bool:
    """Whether the scratch folder ``base`` (default: the system's temporary folder) takes uploads
    (:func:`~service.io.limits.folders_take_writes`); a replica whose scratch is full or read-only
    fails every upload.

    Example:
        >>> import tempfile
        >>> scratch_takes_uploads(Path(tempfile.mkdtemp())), scratch_takes_uploads(Path("/nonexistent/svrnet"))
        (True, False)
    """
    return folders_take_writes(Path(base or tempfile.gettempdir()))


def sweep_stale_uploads(base: Path | None, older_than_s: float) -> int:
    """Delete the service's temporary upload folders in ``base`` (default: the system's temporary
    folder) untouched for over ``older_than_s``: what a server killed mid-request left behind (a live
    request's folder is younger than its upload deadline and its processing). Returns their number.

    Example:
        >>> import os, tempfile
        >>> base = Path(tempfile.mkdtemp()); (base / "svrnet-req-old").mkdir(); (base / "other").mkdir()
        >>> os.utime(base / "svrnet-req-old", (0, 0)); sweep_stale_uploads(base, 3600), sorted(os.listdir(base))
        (1, ['other'])
    """
    root, now, swept = Path(base or tempfile.gettempdir()), time.time(), 0
    try:
        entries = list(root.iterdir())
    except OSError:
        return 0
    for entry in entries:
        try:
            stale = (entry.name.startswith(STALE_PREFIXES) and entry.is_dir() and not entry.is_symlink()
                     and now - entry.stat().st_mtime > older_than_s)
        except OSError:
            continue
        if stale:
            shutil.rmtree(entry, ignore_errors=True)
            swept += 1
    return swept


FORM_NAME_ESCAPES = {"%22": '"', "%0A": "\n", "%0D": "\r"}
"""What browsers, httpx and this project's client write for a quote, a line feed and a carriage return
in a multipart part's ``filename`` (the WHATWG form-data encoding): read back as they were."""


def display_name(upload: UploadFile, field: str, index: int) -> str:
    """The client's file name (for messages to the client only, without control characters; its form
    encoding's escapes read back, :data:`FORM_NAME_ESCAPES`), or ``field[index]``.

    Example:
        >>> from starlette.datastructures import UploadFile
        >>> display_name(UploadFile(None, filename="C:\\\\scans\\\\axial %221%22.nii.gz"), "stacks", 0)
        'axial "1".nii.gz'
        >>> display_name(UploadFile(None, filename=""), "masks", 2)
        'masks[2]'
    """
    name = re.sub("|".join(FORM_NAME_ESCAPES), lambda m: FORM_NAME_ESCAPES[m.group()], upload.filename or "")
    name = clean_name(Path(name.replace("\\", "/")).name)
    return name or f"{field}[{index}]"


@functools.cache
def declared_fields(endpoint: Callable) -> dict[str, bool]:
    """The form and file fields a route function declares (``Annotated[..., Form()]`` / ``File()``),
    its dependencies' included, each with whether it takes several values (a ``list`` field)."""
    hints = typing.get_type_hints(endpoint, include_extras=True)
    out: dict[str, bool] = {}
    for name, hint in hints.items():
        for meta in getattr(hint, "__metadata__", ()):
            if isinstance(meta, params.Form):
                field = typing.get_args(hint)[0]                  # the type, Optional[...] unwrapped below
                out[meta.alias or name] = any(typing.get_origin(a) is list for a in (field, *typing.get_args(field)))
            elif isinstance(meta, params.Depends) and meta.dependency is not None:
                out.update(declared_fields(meta.dependency))
    return out


def known_fields(*extra: str) -> Callable[[Request], Awaitable[None]]:
    """A dependency refusing (400, by name) any form field that the route neither declares nor lists in
    ``extra`` (fields it reads from the raw form), a field of one value given more than once, and a
    field sent empty: a misspelt, misplaced, doubled or blank option is never ignored, silently decided
    by its last copy or taken for its default."""

    async def check(request: Request) -> None:
        declared = declared_fields(request.scope["endpoint"]) | dict.fromkeys(extra, False)
        form = await request.form()       # parsed once: FastAPI reuses it for the route's fields
        unknown = [shown_name(k) for k in dict.fromkeys(form.keys()) if k not in declared]
        if unknown:
            raise InvalidParameter(f"{unknown[0]}: unknown field; this route takes {', '.join(declared)}")
        counts = Counter(k for k, _ in form.multi_items())
        doubled = [k for k, n in counts.items() if n > 1 and not declared[k]]
        if doubled:
            raise InvalidParameter(f"{doubled[0]}: given {counts[doubled[0]]} times; this field takes one value")
        empty = [k for k, v in form.multi_items() if isinstance(v, str) and not v.strip()]
        if empty:                         # FastAPI takes an empty value for an absent one: the default
            raise InvalidParameter(f"{empty[0]}: empty; leave the field out for its default")

    return check


def check_form(stacks: list[UploadFile], masks: list[UploadFile] | None, max_files: int) -> list[UploadFile]:
    """The checks FastAPI's form validation leaves to the routes; returns the masks really given
    (a form with an empty file field sends a nameless, empty part)."""
    if len(stacks) > max_files:
        raise InvalidParameter(f"stacks: {len(stacks)} files; at most {max_files} per request")
    return [m for m in (masks or []) if m.filename or m.size]


MAX_EXPECTED_ERROR_HELP = ("slices whose pose's expected error (mm, after every stage) exceeds it are not "
                           "accepted (reason high_expected_error); default: the model's calibrated value")

def _slice_order_value(value: str) -> str:
    if not re.fullmatch(PATTERN, value):
        raise ValueError(VALUES)
    return value


SliceOrderField = Annotated[str, StringConstraints(max_length=MAX_TEXT), AfterValidator(_slice_order_value),
                            WithJsonSchema({"type": "string", "pattern": PATTERN, "maxLength": MAX_TEXT})]
"""One value of the ``slice_order`` form field (refused with the values it may take, not the pattern)."""
SLICE_ORDER_HELP = ("the stacks' acquisition order, if known: none (the motion model chooses), one value for every "
                    "stack, or one per stack; each auto, interleaved (either phase), sequential, "
                    "interleaved-even-first, interleaved-odd-first, or the slice indices (0-based, along "
                    "slice_axis) in the order they were acquired, comma-separated")


MASKS_HOLD_CSF_HELP = ("the uploaded masks are the skull's inside (brain and the CSF around it, as manual fetal "
                       "masks are usually drawn): the pose network then sees them less their outer 2 mm, as it "
                       "sees the localiser's; default: tight brain masks, used as they are")


@dataclass
class UploadForm:
    """The fields every route that takes stacks for poses shares (``/v1/predict``,
    ``/v1/reconstructions``), checked: the masks really given, one acquisition order per stack."""

    stacks: list[UploadFile]
    masks: list[UploadFile]
    mc_samples: int
    variance_threshold: float | None
    max_expected_error_mm: float | None
    model: str
    slice_order: list[str]
    orders: list[SliceOrder]
    masks_hold_csf: bool = False


async def upload_form(
    settings: SettingsDep,
    stacks: Annotated[list[UploadFile], File(description="1..32 stacks: .nii(.gz), .nrrd, .mha, .dcm or .zip of a DICOM series")],
    masks: Annotated[Optional[list[UploadFile]], File(description="0 or one mask per stack, same grid")] = None,
    mc_samples: Annotated[int, Form(ge=1, le=1000, description="MC-dropout passes per slice")] = 100,
    variance_threshold: Annotated[Optional[float], Form(gt=0, allow_inf_nan=False, description="default: the model's")] = None,
    max_expected_error_mm: Annotated[Optional[float], Form(gt=0, allow_inf_nan=False, description=MAX_EXPECTED_ERROR_HELP)] = None,
    model: Annotated[str, Form(description="a name from GET /v1/models")] = "default",
    slice_order: Annotated[Optional[list[SliceOrderField]], Form(description=SLICE_ORDER_HELP)] = None,
    masks_hold_csf: Annotated[bool, Form(description=MASKS_HOLD_CSF_HELP)] = False,
) -> UploadForm:
    """The shared fields of a request (:class:`UploadForm`); 400 naming the field that is wrong."""
    given = check_form(stacks, masks, settings.max_files)
    return UploadForm(stacks, given, mc_samples, variance_threshold, max_expected_error_mm, model,
                      slice_order or [], parse_orders(slice_order, len(stacks)), masks_hold_csf)


UploadFormDep = Annotated[UploadForm, Depends(upload_form)]


def parse_orders(values: list[str] | None, n_stacks: int) -> list[SliceOrder]:
    """One acquisition order per stack from the ``slice_order`` field (:class:`InvalidParameter` naming
    the value that says nothing known, or a count that is neither 0, 1 nor one per stack)."""
    orders = []
    for i, text in enumerate(values or []):
        try:
            orders.append(SliceOrder.parse(text))
        except ValueError as e:
            raise InvalidParameter(f"slice_order[{i}]: {e}") from None
    try:
        return per_stack(orders, n_stacks)
    except ValueError as e:
        raise InvalidParameter(f"slice_order: {e}") from None


def upload_reader(settings: Settings, masks_hold_csf: bool = False) -> Callable[..., list[StackUpload]]:
    """:func:`save_and_read` with this server's limits (decoding, slices per stack): called with the
    stacks, the masks and the folder they go to."""
    return functools.partial(save_and_read, max_decoded_bytes=settings.max_decoded_bytes,
                             max_request_bytes=settings.max_request_decoded_bytes, masks_hold_csf=masks_hold_csf,
                             max_slices=settings.max_slices_per_stack)


def save_and_read(stacks: list[UploadFile], masks: list[UploadFile], directory: Path,
                  max_decoded_bytes: int = MAX_DECODED_BYTES, max_request_bytes: int | None = None,
                  masks_hold_csf: bool = False, max_slices: int | None = None) -> list[StackUpload]:
    """Write each upload to ``directory`` and read it (blocking: run in a worker thread); the masks
    are the skull's inside with ``masks_hold_csf``, each brought into its stack's voxel order where its
    file stores the stack's voxels in another (:func:`~service.pipeline.stack_upload.mask_on_stack_grid`);
    a stack of more than ``max_slices`` slices is refused (422 naming the file).

    Each file may decode to ``max_decoded_bytes``, all of them together to ``max_request_bytes``
    (:class:`~service.io.limits.DecodeBudget`): many bombs in one request stop at the request's limit.
    """
    budget = DecodeBudget(max_decoded_bytes, max_request_bytes, max_slices)
    if masks and len(masks) != len(stacks):
        raise InvalidParameter(f"masks: {len(masks)} masks for {len(stacks)} stacks; give none or one per stack")
    jobs = [(up, directory / f"stack{i}", display_name(up, "stacks", i), True) for i, up in enumerate(stacks)]
    jobs += [(up, directory / f"mask{i}", display_name(up, "masks", i), False) for i, up in enumerate(masks)]
    # Decompression and parsing release the GIL: read two files at a time. Errors surface in
    # upload order, as a sequential loop would raise them; the map's futures not yet begun are then
    # cancelled, so the files after a failed one are not read.
    with ThreadPoolExecutor(max_workers=READ_WORKERS) as pool:
        volumes = list(pool.map(carried(lambda job: _read(*job[:3], budget, job[3])), jobs))
    n = len(stacks)
    for (_, _, name, _), volume in zip(jobs[:n], volumes[:n]):
        axis = slice_axis_of(volume.spacing)
        count = volume.array.shape[axis]
        if max_slices is not None and count > max_slices:
            voxels = " x ".join(f"{s:.3g}" for s in volume.spacing)
            raise UnusableImage(f"{name}: {count} slices along its array axis {axis}, the axis of largest "
                                f"spacing (voxels of {voxels} mm); at most {max_slices} in one stack of 2D slices "
                                "(SVRNET_MAX_SLICES_PER_STACK)")
    return [mask_on_stack_grid(StackUpload(jobs[i][2], volumes[i], volumes[n + i] if masks else None,
                                           jobs[n + i][2] if masks else None, mask_holds_csf=masks_hold_csf))
            for i in range(n)]


def _read(upload: UploadFile, path: Path, name: str, budget: DecodeBudget, image: bool = True):  # noqa: ANN202
    """Write one upload to ``path`` and read it: a stack's values as magnitudes, a mask's as they are
    (``image`` False; what is wrong with it is said of ``masks: <name>``). The form parser's spooled
    copy is closed (deleted) once written, so that a request keeps its files on disk once, not twice."""
    checkpoint()
    upload.file.seek(0)
    try:
        with open(path, "wb") as f:
            shutil.copyfileobj(upload.file, f, 1 << 20)
    except OSError as exc:
        raise_if_out_of_space(exc)        # a full disk is the server's (507), not the client's file
        raise
    finally:
        upload.file.close()
    said = name if image else f"masks: {name}"   # a stack and its mask share names: a mask's problems name the field
    with DECODING:
        return read_upload(path, said, budget=budget.file(said), scratch=path.parent, magnitudes=image)
