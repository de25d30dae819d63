"""The catch-all: an unexpected exception is a logged 500 JSON, and the service lives on.

No client mistake reaches this path (test_service_errors.py checks that), so the test
adds one failing route to a real app served by a real uvicorn on 127.0.0.1.
"""

from __future__ import annotations

import logging
import socket
import threading
import time

import httpx
import pytest
import uvicorn
from scenesort.backend.api.app import create_app
from scenesort.backend.api.service import Settings
from scenesort.backend.commands.serve import _listen


@pytest.fixture
def failing_service():
    app = create_app(Settings())

    @app.get("/v1/boom")
    async def boom() -> dict:
        raise RuntimeError("engine exploded")

    sock = _listen(socket.AF_INET, "127.0.0.1", 0)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", access_log=False))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    for _ in range(100):  # bounded: 10 s
        if server.started:
            break
        time.sleep(0.1)
    yield url
    server.should_exit = True
    thread.join(timeout=10)


def test_unexpected_error_is_a_logged_500_and_health_stays_200(failing_service, caplog):
    with caplog.at_level(logging.ERROR, logger="scenesort.app"):
        response = httpx.get(f"{failing_service}/v1/boom", timeout=10)
    assert response.status_code == 500
    assert response.json()["type"].endswith(":internal_error")
    assert "RuntimeError" in response.json()["detail"]
    assert "engine exploded" not in response.text  # details go to the log, not the client
    assert any("internal error on GET /v1/boom" in r.getMessage() for r in caplog.records)
    assert httpx.get(f"{failing_service}/v1/health", timeout=10).status_code == 200
