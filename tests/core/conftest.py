"""Fixtures of the core tests: the tiny exported model of the API tests."""

from tests.api.conftest import tiny_model_path  # noqa: F401 - fixture
