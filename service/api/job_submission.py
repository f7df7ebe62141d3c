"""What a reconstruction job's submission must pass before its job is queued: the slice thickness
per stack, the ``poses`` upload's bounds and its reading, and the slices the job could start from
(4xx naming the field or the file otherwise).

Example:
    >>> thickness_per_stack([2.5], 3), thickness_per_stack(None, 2)
    ([2.5, 2.5, 2.5], [None, None])
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field

from service.api.schemas import job_poses
from service.consistency.slice_order import SliceOrder
from service.core.client_json import client_json
from service.core.errors import InvalidParameter, PayloadTooLarge, UnusableImage
from service.io.acquisition_geometry import MAX_VOXEL_MM, MIN_VOXEL_MM
from service.jobs.job_inputs import keep_json
from service.jobs.starting_poses import uploaded_start
from service.jobs.uploaded_poses import in_upload_order, poses_from_predict_body
from service.pipeline.predict import stack_orders
from service.pipeline.stack_upload import StackUpload, check_uploads, marked_brain
from service.reconstruction.config import ReconstructionConfig
from service.reconstruction.grid import check_brain_fits


ThicknessField = Annotated[float, Field(ge=MIN_VOXEL_MM, le=MAX_VOXEL_MM, allow_inf_nan=False)]
"""One value of the ``slice_thickness_mm`` form field (mm)."""
SLICE_THICKNESS_HELP = ("the slices' thickness (mm), the width of each slice's profile in the reconstruction: one "
                        "value for every stack or one per stack; default: what a DICOM file states (SliceThickness), "
                        "else the slice spacing (right for contiguous slices; give it for slices with gaps or overlap)")


def thickness_per_stack(values: list[float] | None, n_stacks: int) -> list[float | None]:
    """One slice thickness per stack (None: the file's, else the spacing) from the form's values, each
    already within :data:`ThicknessField`'s bounds (:class:`InvalidParameter` naming the field for a
    count that is neither one nor one per stack)."""
    if not values:
        return [None] * n_stacks
    if len(values) not in (1, n_stacks):
        raise InvalidParameter(f"slice_thickness_mm: {len(values)} values for {n_stacks} stacks; give one for every "
                               "stack or one per stack")
    return list(values) * n_stacks if len(values) == 1 else list(values)


POSES_BYTES_PER_SLICE = 16 << 10
"""What a ``poses`` upload may hold per slice of the uploaded stacks (and 64 KB besides), JSON
objects and arrays included (:data:`POSES_CONTAINERS_PER_SLICE`), checked before it is decoded:
``/v1/predict`` writes about 3 KB, 1.3 objects and 22 arrays a slice, while small JSON objects
decode to twenty times their text (64 MB of ``{}`` held 1.5 GB)."""
POSES_CONTAINERS_PER_SLICE = 64


def checked_poses(text: str, uploads: list[StackUpload]) -> tuple[dict, list[tuple[np.ndarray, np.ndarray]]]:
    """A ``poses`` upload as the job keeps it (:func:`~service.api.schemas.job_poses`) and the poses and
    accepted flags the worker will read from it, per stack (blocking: run in a worker thread);
    :class:`InvalidParameter` naming what does not match the uploads; :class:`PayloadTooLarge` where
    the text holds more than such poses could (:data:`POSES_BYTES_PER_SLICE`), before it is decoded."""
    if text.lstrip()[:1] not in ("{", "["):         # an image sent as poses: said so, not measured as JSON
        raise InvalidParameter("poses: not JSON; poses are the JSON answer of /v1/predict for these stacks "
                               "(svrnet predict --out)")
    slices = sum(u.volume.array.shape[u.slice_axis] for u in uploads)
    containers = text.count("{") + text.count("[")
    if len(text) > POSES_BYTES_PER_SLICE * slices + (64 << 10) or containers > POSES_CONTAINERS_PER_SLICE * slices + 256:
        raise PayloadTooLarge(f"poses: {len(text)} characters, {containers} JSON objects and arrays for the "
                              f"{slices} slices of the uploaded stacks; /v1/predict's poses take about 3 KB and "
                              "23 objects and arrays a slice")
    try:
        body = client_json(text)
    except ValueError as exc:
        raise InvalidParameter("poses: not valid JSON") from exc
    counts = [u.volume.array.shape[u.slice_axis] for u in uploads]
    affines = [u.volume.affine for u in uploads]
    try:
        body = in_upload_order(body, [u.filename for u in uploads])
        poses_from_predict_body(body, counts, affines)
    except ValueError as exc:
        raise InvalidParameter(str(exc)) from exc
    kept = job_poses(body)
    try:
        return kept, poses_from_predict_body(kept, counts, affines)          # what the worker will read
    except ValueError as exc:
        raise InvalidParameter(f"{exc} (as /v1/predict writes them: numbers as JSON numbers, accepted as "
                               "true or false)") from exc


def check_slices_to_use(uploads: list[StackUpload], accepted: list[np.ndarray] | None) -> None:
    """Refuse now a job that would fail for want of slices: every stack has its mask, and no slice the
    job may use (an accepted one, where poses are given) holds a voxel of it. Without a mask (or with
    a region around the head) the worker's localiser decides."""
    if any(u.localised for u in uploads):
        return
    holding, showing = [], []                     # per stack: which slices hold a voxel of its mask; and an image there
    for u in uploads:
        inside = np.moveaxis(u.mask_voxels, u.slice_axis, 0).reshape(u.volume.array.shape[u.slice_axis], -1)
        pixels = np.moveaxis(u.volume.array, u.slice_axis, 0).reshape(inside.shape)
        holding.append(inside.any(1))
        showing.append(np.where(inside, pixels, -np.inf).max(1) > np.where(inside, pixels, np.inf).min(1))
    if not any(h.any() for h in holding):
        raise UnusableImage(f"masks: no mask holds a voxel ({', '.join(str(u.mask_filename) for u in uploads)}); "
                            "there is nothing to reconstruct")
    if not any(s.any() for s in showing):
        raise UnusableImage(f"stacks: no slice shows an image inside its mask (the pixels there are all alike: "
                            f"{', '.join(u.filename for u in uploads)}); there is nothing to reconstruct")
    holding = [h & s for h, s in zip(holding, showing)]
    if accepted is not None and not any((h & np.asarray(a, bool)).any() for h, a in zip(holding, accepted)):
        raise InvalidParameter("poses: no accepted slice holds a voxel of its stack's mask; there is nothing to "
                               "reconstruct")


def check_submission(uploads: list[StackUpload], orders: list[SliceOrder], poses_text: str | None, inputs: Path,
                     resolution_mm: float) -> None:
    """The checks a submission's read files must pass before its job is queued, and its ``poses``
    kept in ``inputs`` (blocking: run in a worker thread); 4xx naming what is wrong."""
    stack_orders(orders, uploads)
    given = None
    if poses_text:
        kept, given = checked_poses(poses_text, uploads)
        keep_json(kept, inputs / "poses.json")
    check_uploads(uploads)
    brain_mm3, extent = max((marked_brain(u) for u in uploads if not u.mask_is_region), key=lambda marked: marked[0],
                            default=(0.0, np.zeros(3)))                 # a region's brain is the localiser's to find
    check_brain_fits(brain_mm3, extent, resolution_mm, ReconstructionConfig().margin_mm)
    starts = None if given is None else [include for _, include in uploaded_start(kept, given)[0]]
    check_slices_to_use(uploads, starts)
