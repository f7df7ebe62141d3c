from fastapi.testclient import TestClient

from service.main import create_app


def test_healthz() -> None:
    with TestClient(create_app()) as client:
        r = client.get("/healthz")
    assert r.status_code == 200 and r.json() == {"status": "ok"}
