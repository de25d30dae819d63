"""The catch-all: an unexpected exception is a logged 500 JSON, and the service lives on.

No client mistake reaches this path (test_service_errors.py checks that), so the test
adds one failing route to a real app served by a real uvicorn on 127.0.0.1.
"""

from __future__ import annotations

import logging

import httpx
import pytest
from gated import serve
from scenesort.backend.api.app import create_app
from scenesort.backend.api.service import Settings


@pytest.fixture
def failing_service():
    app = create_app(Settings())

    @app.get("/v1/boom")
    async def boom() -> dict:
        raise RuntimeError("engine exploded")

    with serve(app) as running:
        yield running.url


def test_unexpected_error_is_a_logged_500_and_health_stays_200(failing_service, caplog):
    with caplog.at_level(logging.ERROR, logger="scenesort.app"):
        response = httpx.get(f"{failing_service}/v1/boom", timeout=10)
    assert response.status_code == 500
    assert response.json()["type"].endswith(":internal_error")
    assert "RuntimeError" in response.json()["detail"]
    assert "engine exploded" not in response.text  # details go to the log, not the client
    assert any("internal error on GET /v1/boom" in r.getMessage() for r in caplog.records)
    assert httpx.get(f"{failing_service}/v1/health", timeout=10).status_code == 200
