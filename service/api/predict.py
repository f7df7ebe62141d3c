"""``POST /v1/predict``: stacks in, per-slice atlas poses with confidence out."""

from __future__ import annotations

import time
from typing import Annotated

from anyio import to_thread
from fastapi import APIRouter, Depends, Form, Request

from service.api.deps import (ApiKey, LocalisersDep, MetricsDep, RegistryDep, SettingsDep, localiser_for,
                              localiser_for_regions, processing, requested_model)
from service.api.schemas import UPLOAD_ERRORS, PredictResponse
from service.api.uploads import UploadFormDep, known_fields, upload_directory, upload_reader
from service.pipeline.documents import stack_objects
from service.pipeline.predict import predict as run_prediction
from service.pipeline.prepare import prepare_stacks

router = APIRouter(prefix="/v1", tags=["prediction"], dependencies=[ApiKey])


@router.post("/predict", response_model=PredictResponse, responses=UPLOAD_ERRORS, summary="Atlas pose of every slice",
             dependencies=[Depends(known_fields())])
async def predict(
    request: Request,
    registry: RegistryDep,
    localisers: LocalisersDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    form: UploadFormDep,
    bias_correction: Annotated[bool, Form(description="N4 before normalisation")] = True,
    stack_consistency: Annotated[bool, Form(description="decide each stack's left-right branch from all its slices, "
                                                        "fit a motion-tolerant stack model, flag inconsistent slices")] = True,
    image_consistency: Annotated[bool, Form(description="refine the poses of the settled stacks where their slices "
                                                        "cross (their images must agree there); needs stack_consistency "
                                                        "and two stacks that decided their left-right branch")] = True,
) -> dict:
    """Every slice of every stack, accepted or not, in order, with its SE(3) Fréchet-mean pose (the work
    stops at its next step where the client leaves)."""
    t0 = time.perf_counter()
    model = requested_model(request, registry, form.model)
    estimator = registry.get(model)
    localiser = localiser_for(localisers, form.masks)
    info = estimator.info
    threshold = form.variance_threshold if form.variance_threshold is not None else info.variance_threshold
    max_expected = form.max_expected_error_mm if form.max_expected_error_mm is not None else info.max_expected_error_mm
    async with processing(request):
        with upload_directory(settings.tmp_dir) as tmp:
            uploads = await to_thread.run_sync(upload_reader(settings, form.masks_hold_csf), form.stacks, form.masks,
                                               tmp)
        localiser = localiser or localiser_for_regions(localisers, uploads)    # a box around the head: searched
        t_read = time.perf_counter()
        prepared = await to_thread.run_sync(prepare_stacks, uploads, estimator.info, bias_correction,
                                            settings.preprocess_workers, localiser)
        t_prep = time.perf_counter()
        predictions, timings = await to_thread.run_sync(run_prediction, prepared, estimator, form.mc_samples,
                                                        threshold, stack_consistency, form.orders, image_consistency,
                                                        max_expected)
    metrics.observe_slices(model, [r for p in predictions for r in p.reasons])
    stage = lambda key: sum(p.timings.get(key, 0.0) for p in prepared)  # noqa: E731 - CPU time summed over stacks
    return {
        "request_id": request.scope["state"]["request_id"],
        "model": info.reference(model),
        "mc_samples": form.mc_samples, "variance_threshold": threshold, "max_expected_error_mm": max_expected,
        "localiser": None if localiser is None else localiser.provenance(),
        "stacks": stack_objects(predictions),
        "timing_ms": {
            "read": (t_read - t0) * 1e3, "localisation": stage("localisation") * 1e3,
            "bias_correction": stage("bias_correction") * 1e3, "preprocess": (t_prep - t_read) * 1e3,
            "inference": timings.get("inference", 0.0) * 1e3, "statistics": timings.get("statistics", 0.0) * 1e3,
            "stack_consistency": timings.get("stack_consistency", 0.0) * 1e3,
            "image_consistency": timings.get("image_consistency", 0.0) * 1e3, "total": (time.perf_counter() - t0) * 1e3,
        },
    }
