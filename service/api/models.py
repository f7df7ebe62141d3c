"""``GET /v1/models``."""

from __future__ import annotations

from fastapi import APIRouter

from service.api.deps import ApiKey, RegistryDep
from service.api.schemas import ModelDescription, problem_responses

router = APIRouter(prefix="/v1", tags=["models"], dependencies=[ApiKey])


@router.get("/models", response_model=list[ModelDescription], responses=problem_responses(401), summary="Models this server offers")
async def list_models(registry: RegistryDep) -> list[dict]:
    """Name, version, backbone, checksum, input geometry, label type, default variance threshold."""
    return registry.describe()
