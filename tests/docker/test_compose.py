"""``docker/compose.yaml`` cannot be run here (no container engine): parse it and check that it says
what docs/deployment.md promises -- Redis, two API replicas behind one port, two workers, one shared volume,
a health check per service -- and that every command it runs exists in this package."""

from __future__ import annotations

import contextlib
import io
import re
import tomllib
from pathlib import Path

import yaml

from service.jobs.worker_cli import main
from tests.support.local_client import LocalClient

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
SERVICES = COMPOSE["services"]


def _svrnet_services() -> dict[str, dict]:
    return {name: s for name, s in SERVICES.items() if s.get("image", "").startswith("svrnet")}


def test_the_services_and_their_health_checks() -> None:
    assert {"redis", "api-1", "api-2", "worker", "lb"} <= set(SERVICES)
    for name, service in SERVICES.items():
        test = service.get("healthcheck", {}).get("test")
        assert isinstance(test, list) and test[0] == "CMD" and len(test) > 1, name
    assert SERVICES["worker"]["deploy"]["replicas"] == 2
    assert SERVICES["lb"]["ports"] == ["${SVRNET_BIND:-127.0.0.1}:8000:8000"]     # this host only, unless told
    assert [n for n, s in _svrnet_services().items() if "ports" in s] == ["mrd"]     # MRD speaks TCP, not HTTP


def test_every_command_exists() -> None:
    svrnet = _svrnet_services()
    assert {"api-1", "api-2", "worker", "mrd"} == set(svrnet)
    for name, service in svrnet.items():
        assert service["command"][0] in SCRIPTS, (name, service["command"])
        assert service["build"]["dockerfile"] == "docker/Dockerfile"
    assert [SERVICES[n]["command"] for n in ("api-1", "api-2")] == [["svrnet-server"]] * 2
    assert SERVICES["worker"]["command"] == ["svrnet-worker"]
    assert SERVICES["mrd"]["command"][0] == "svrnet-mrd"
    assert SERVICES["mrd"]["ports"] == ["${SVRNET_MRD_BIND:-127.0.0.1}:9002:9002"]    # its own: opening the API leaves it closed
    assert SERVICES["worker"]["healthcheck"]["test"][1:] == ["svrnet-worker", "--health"]
    out = io.StringIO()                               # the worker's option parser knows those options
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        main(["--help"])
    assert "--health" in out.getvalue() and "--workers" in out.getvalue()
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    assert re.search(r'pip install .*"\.\[server,queue\]"', dockerfile)
    assert 'CMD ["svrnet-server"]' in dockerfile


def test_one_queue_and_one_shared_volume_for_api_and_workers() -> None:
    for name, service in _svrnet_services().items():
        env = service["environment"]
        assert env["SVRNET_QUEUE_URL"].startswith("redis://redis:"), name
        assert f"svrnet-data:{env['SVRNET_DATA_DIR']}" in service["volumes"], name
        assert service["depends_on"]["redis"]["condition"] == "service_healthy"
    assert "svrnet-data" in COMPOSE["volumes"]


def test_the_load_balancer_sends_to_both_replicas() -> None:
    mount = SERVICES["lb"]["volumes"][0].split(":")
    conf = (ROOT / "docker" / mount[0]).read_text()
    assert re.findall(r"server\s+([\w-]+):8000", conf) == ["api-1", "api-2"]
    assert re.search(r"proxy_pass\s+http://svrnet_api;", conf) and "listen 8000;" in conf
    stream = conf[conf.index("location /v1/stream"):]                        # WebSockets pass the upgrade
    assert "proxy_set_header Upgrade $http_upgrade;" in stream and "$connection_upgrade" in stream
    assert set(SERVICES["lb"]["depends_on"]) == {"api-1", "api-2"}


def test_the_load_balancer_passes_the_host_with_its_port() -> None:
    """A server without keys serves its own pages' requests: their ``Origin`` (``http://127.0.0.1:8000``)
    must equal the ``Host`` it receives. nginx's ``$host`` drops the port (``127.0.0.1``), which made
    every browser request of the OpenAPI page behind the load balancer a 403; ``$http_host`` keeps it."""
    from service.core.settings import Settings
    from service.inference.registry import ModelRegistry
    from service.main import create_app

    conf = (ROOT / "docker" / SERVICES["lb"]["volumes"][0].split(":")[0]).read_text()
    passed = re.findall(r"^\s*proxy_set_header\s+Host\s+(\S+);", conf, re.MULTILINE)
    assert passed and set(passed) == {"$http_host"}, passed
    published = "127.0.0.1:8000"                               # the browser's address of the load balancer
    as_passed = {"$http_host": published, "$host": published.rsplit(":", 1)[0]}
    app = create_app(Settings(api_keys="", allowed_origins=""), registry=ModelRegistry({}))
    with LocalClient(app, raise_server_exceptions=False) as client:
        for variable in ("$http_host", "$host"):
            r = client.get("/v1/models", headers={"Origin": f"http://{published}", "Host": as_passed[variable]})
            assert (r.status_code == 403) == (variable == "$host"), (variable, r.status_code)


def test_the_load_balancer_lets_the_requests_under_way_finish_and_leaves_upload_limits_to_the_service() -> None:
    """compose stops the service others depend on first: with its default 10 s, a prediction under way
    was cut at the proxy while its replica had 75 s. nginx's own 413 (HTML, no request id) answered
    any body over its fixed size, whatever SVRNET_MAX_UPLOAD_MB said."""
    def seconds(text: str) -> float:
        return float(re.fullmatch(r"(\d+)s", text).group(1))

    assert seconds(SERVICES["lb"]["stop_grace_period"]) >= seconds(SERVICES["api-1"]["stop_grace_period"])
    sizes = re.findall(r"^\s*client_max_body_size\s+(\S+);", (ROOT / "docker" / "nginx.conf").read_text(), re.M)
    assert sizes == ["0"]


def test_every_variable_compose_reads_is_one_the_services_know() -> None:
    """Those compose substitutes from the operator's shell are not the service's settings: the service,
    started from that shell, would otherwise warn that nothing reads them."""
    from service.core.settings import unknown_variables

    read = set(re.findall(r"\$\{(SVRNET_[A-Z_]+)", (ROOT / "docker" / "compose.yaml").read_text()))
    assert read and unknown_variables(dict.fromkeys(read, "x")) == []
