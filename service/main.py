"""The application factory and its lifespan; nothing else lives here.

Run with ``svrnet-server`` (or ``make serve``); settings come from ``SVRNET_*`` variables.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from service.api import health
from service.core.settings import Settings


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the FastAPI app for ``settings`` (default: from the environment)."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.settings = settings
        yield

    app = FastAPI(title="SVRnet", version="0.1.0", lifespan=lifespan,
                  description="Slice-to-atlas pose estimation for fetal MRI with MC-dropout confidence.")
    app.include_router(health.router)
    return app


def run() -> None:
    """Console entry point: serve :func:`create_app` with uvicorn on ``SVRNET_HOST:SVRNET_PORT``."""
    import uvicorn

    settings = Settings()
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=settings.log_level)
