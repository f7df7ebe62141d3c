"""``GET /v1/models`` and ``GET /v1/localisers``: the models this server offers."""

from __future__ import annotations

from fastapi import APIRouter

from service.api.deps import ApiKey, LocalisersDep, RegistryDep
from service.api.schemas import LocaliserDescription, ModelDescription, problem_responses

router = APIRouter(prefix="/v1", tags=["models"], dependencies=[ApiKey])


@router.get("/models", response_model=list[ModelDescription], responses=problem_responses(401), summary="Models this server offers")
async def list_models(registry: RegistryDep) -> list[dict]:
    """Name, version, backbone, checksum, input geometry, label type, default variance threshold,
    the training data's licences and whether the model's card is there."""
    return registry.describe()


@router.get("/localisers", response_model=list[LocaliserDescription], responses=problem_responses(401),
            summary="Brain localisers this server offers")
async def list_localisers(localisers: LocalisersDep) -> list[dict]:
    """Name, version, checksum, grid, licences and card of each localiser; ``default`` marks the one
    stacks sent without masks go to (``/v1/masks``' ``model`` names another)."""
    return localisers.describe()
