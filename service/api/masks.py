"""``POST /v1/masks``: brain masks for stacks as they leave the scanner (the service's localiser)."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Annotated

from anyio import to_thread
from fastapi import APIRouter, Depends, File, Form, Response, UploadFile

from service.api.deps import ApiKey, LocalisersDep, SettingsDep, SlotDep
from service.api.schemas import UPLOAD_ERRORS
from service.api.uploads import check_form, known_fields, save_and_read, upload_directory
from service.core.names import unique_stems
from service.io.nifti_header import copy_transforms
from service.io.volume import Volume, write_volume
from service.preprocess.localise import Localiser

router = APIRouter(prefix="/v1", tags=["masks"], dependencies=[ApiKey])


def masks_archive(uploads: list, localiser: Localiser, directory: Path) -> bytes:
    """The zip of one ``<stem>_mask.nii.gz`` per stack (its own grid) and ``report.json``."""
    report = []
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        located = localiser.localise_many([u.volume for u in uploads])
        for upload, stem, found in zip(uploads, unique_stems([u.filename for u in uploads]), located):
            path = directory / f"{stem}_mask.nii.gz"
            write_volume(Volume(found.mask.astype("uint8"), upload.volume.affine), path)
            if upload.volume.nifti is not None:          # the upload's own transforms: overlays in any viewer
                copy_transforms(path, upload.volume.nifti)
            archive.write(path, path.name)
            path.unlink()
            report.append({"filename": upload.filename, "mask": path.name, **found.report(),
                           "slices_with_brain": found.slices_with_brain})
        archive.writestr("report.json", json.dumps({"localiser": {"version": localiser.version,
                                                                  "sha256": localiser.sha256},
                                                    "stacks": report}, indent=1))
    return buffer.getvalue()


@router.post("/masks", responses={200: {"content": {"application/zip": {}}}, **UPLOAD_ERRORS},
             response_class=Response, summary="Brain masks of stacks sent without one",
             dependencies=[Depends(known_fields())])
async def masks(
    localisers: LocalisersDep,
    settings: SettingsDep,
    _slot: SlotDep,
    stacks: Annotated[list[UploadFile], File(description="1..32 stacks, as for /v1/predict")],
    model: Annotated[str, Form(description="the localiser's name")] = "default",
) -> Response:
    """One NIfTI mask per stack on the stack's own grid (uint8 0/1) and ``report.json``, zipped."""
    localiser = localisers.get(model)
    check_form(stacks, None, None, settings.max_files)
    with upload_directory(settings.tmp_dir) as tmp:
        uploads = await to_thread.run_sync(save_and_read, stacks, [], tmp, settings.max_decoded_bytes,
                                           settings.max_request_decoded_bytes)
        body = await to_thread.run_sync(masks_archive, uploads, localiser, tmp)
    return Response(body, media_type="application/zip",
                    headers={"Content-Disposition": 'attachment; filename="masks.zip"'})
