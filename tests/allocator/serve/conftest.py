"""A real ``agv serve`` on 127.0.0.1 (a free port), in a child process, for the service tests."""

from __future__ import annotations

import pytest

pytest.importorskip("fastapi", reason="the service tests need the [serve] extra")
httpx = pytest.importorskip("httpx", reason="the service tests need the [serve] extra")

from allocator.serve.process import ServiceProcess  # noqa: E402


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory):
    """A service on warehouse-20 with no simulator: the tests play the fleet."""
    folder = tmp_path_factory.mktemp("serve")
    svc = ServiceProcess(folder, ["--floor", "warehouse-20", "--method", "hungarian"])
    svc.start()
    yield svc
    svc.stop()


@pytest.fixture
def client(service: ServiceProcess):
    with httpx.Client(base_url=service.url, headers=service.headers, timeout=10.0) as c:
        yield c
