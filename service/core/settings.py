"""All runtime settings, read once from ``SVRNET_*`` environment variables (pydantic-settings).

Example:
    >>> import os
    >>> os.environ["SVRNET_PORT"] = "9000"
    >>> Settings().port
    9000
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

DEFAULT_MODELS_DIR = Path(__file__).resolve().parents[1] / "models"


class Settings(BaseSettings):
    """Service settings; every field can be set as ``SVRNET_<FIELD>`` (case-insensitive)."""

    model_config = SettingsConfigDict(env_prefix="SVRNET_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    models_dir: Path = DEFAULT_MODELS_DIR
    default_model: str = "default"
    log_level: str = "info"
