"""``POST /v1/masks``: brain masks for stacks as they leave the scanner (the service's localiser)."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Annotated

from anyio import to_thread
from fastapi import APIRouter, Depends, File, Form, Request, Response, UploadFile

from service.api.deps import ApiKey, LocalisersDep, SettingsDep, processing
from service.api.schemas import UPLOAD_ERRORS
from service.api.uploads import check_form, known_fields, upload_directory, upload_reader
from service.core.names import MAX_NAME, unique_stems
from service.io.nifti_header import copy_transforms
from service.io.volume import Volume, write_volume
from service.preprocess.localisation import Localisation, grown
from service.preprocess.localise import Localiser
from service.preprocess.intensity import check_stack_values
from service.preprocess.localiser_inputs import check_search

router = APIRouter(prefix="/v1", tags=["masks"], dependencies=[ApiKey])


MASK_SUFFIX = "_mask.nii.gz"
"""Each mask's name in the archive: its stack's stem and this (the whole within :data:`MAX_NAME`, a
file system's limit)."""
MAX_MARGIN_MM = 20.0
MARGIN_HELP = ("grow each mask outward by this many mm (Euclidean, on the stack's voxel sizes): the localiser's "
               "masks are the skull's inside; 2-4 mm reaches masks drawn to the skull's outer edge")


def masks_archive(uploads: list, localiser: Localiser, directory: Path, margin_mm: float = 0.0) -> bytes:
    """The zip of one ``<stem>_mask.nii.gz`` per stack (its own grid), grown by ``margin_mm``
    (:func:`~service.preprocess.localisation.grown`), and ``report.json``."""
    check_stack_values([(u.filename, u.volume.array) for u in uploads])
    check_search([(u.filename, u.volume) for u in uploads])
    report = []
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        located = localiser.localise_many([u.volume for u in uploads])
        stems = unique_stems([u.filename for u in uploads], MAX_NAME - len(MASK_SUFFIX))
        for k, (upload, stem, found) in enumerate(zip(uploads, stems, located)):
            if margin_mm > 0 and found.mask.any():
                found = Localisation.of(grown(found.mask, upload.volume.spacing, margin_mm), upload.volume.spacing,
                                        found.method, found.confidence, found.holds_csf)
            path, member = directory / f"mask{k}.nii.gz", f"{stem}{MASK_SUFFIX}"   # no client name on disk
            write_volume(Volume(found.mask.astype("uint8"), upload.volume.affine), path)
            if upload.volume.nifti is not None:          # the upload's own transforms: overlays in any viewer
                copy_transforms(path, upload.volume.nifti)
            archive.write(path, member)
            path.unlink()
            report.append({"filename": upload.filename, "mask": member, **found.report(),
                           "slices_with_brain": found.slices_with_brain, "margin_mm": margin_mm,
                           "localiser": {"version": localiser.version, "sha256": localiser.sha256}})
        archive.writestr("report.json", json.dumps(report, indent=1))     # api-v1: an object per stack
    return buffer.getvalue()


@router.post("/masks", responses={200: {"content": {"application/zip": {}}}, **UPLOAD_ERRORS},
             response_class=Response, summary="Brain masks of stacks sent without one",
             dependencies=[Depends(known_fields())])
async def masks(
    request: Request,
    localisers: LocalisersDep,
    settings: SettingsDep,
    stacks: Annotated[list[UploadFile], File(description="1..32 stacks, as for /v1/predict")],
    model: Annotated[str, Form(description="the localiser's name")] = "default",
    margin_mm: Annotated[float, Form(ge=0.0, le=MAX_MARGIN_MM, allow_inf_nan=False, description=MARGIN_HELP)] = 0.0,
) -> Response:
    """One NIfTI mask per stack on the stack's own grid (uint8 0/1) and ``report.json``, zipped."""
    localiser = localisers.get(model)
    check_form(stacks, None, settings.max_files)
    async with processing(request):
        with upload_directory(settings.tmp_dir) as tmp:
            uploads = await to_thread.run_sync(upload_reader(settings), stacks, [], tmp)
            body = await to_thread.run_sync(masks_archive, uploads, localiser, tmp, margin_mm)
    return Response(body, media_type="application/zip",
                    headers={"Content-Disposition": 'attachment; filename="masks.zip"'})
