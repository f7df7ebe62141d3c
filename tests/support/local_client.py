"""The tests' ``TestClient`` of the app, at an address."""

from __future__ import annotations

from typing import Any
from urllib.parse import urljoin

from fastapi.testclient import TestClient


class LocalClient(TestClient):
    """A ``TestClient`` that reaches the app at ``127.0.0.1``, HTTP and WebSocket alike: a server without
    API keys answers at an address (:func:`service.api.access.origin_ok`), not at Starlette's default
    host name ``testserver``."""

    def __init__(self, app: Any, **kwargs: Any) -> None:
        super().__init__(app, **{"base_url": "http://127.0.0.1", **kwargs})

    def websocket_connect(self, url: str, *args: Any, **kwargs: Any) -> Any:
        return super().websocket_connect(urljoin("ws://127.0.0.1", url), *args, **kwargs)
