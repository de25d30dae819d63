"""The HTTP client against a real (tiny, standard-library) HTTP server on 127.0.0.1."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from addon import client

# Held by the health handler until the test ends: a service slower than any client timeout.
_HELD = threading.Event()


class _Handler(BaseHTTPRequestHandler):
    """Answers like the service does in its error cases."""

    def log_message(self, *args: object) -> None:  # keep the test output clean
        pass

    def _send(self, status: int, body: bytes, content_type: str = "application/json") -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self) -> None:  # noqa: N802 - http.server's naming
        if self.path == "/v1/health":
            _HELD.wait(60.0)  # no answer while the client waits, nor after
            return
        if "/result?" in self.path:
            self._send(200, b"\0" * 12, "application/octet-stream")  # 3 values, not 2
            return
        self._send(200, b"{}")

    def do_HEAD(self) -> None:  # noqa: N802
        self.send_response(404 if "unknown" in self.path else 200)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def do_POST(self) -> None:  # noqa: N802
        length = int(self.headers.get("Content-Length", 0))
        self.rfile.read(length)
        if self.path.startswith("/v1/scenes?"):
            error = {"type": "tag:scenesort,2026:not_finite", "title": "Bad Request",
                     "status": 400, "parameter": "body (vertices)",
                     "detail": "vertex 3 is not finite ([nan, 0.0, 0.0])",
                     "fix": "replace NaN/Inf values in vertex 3"}  # fmt: skip
            self._send(400, json.dumps(error).encode(), "application/problem+json")
        else:
            self._send(500, b"not json")


@pytest.fixture(scope="module")
def server() -> Iterator[str]:
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        _HELD.set()
        httpd.shutdown()
        httpd.server_close()


def test_service_error_message_and_fix_reach_the_user(server: str) -> None:
    with pytest.raises(client.ServiceError) as err:
        client.Client(server).upload_scene(4, 1, b"\0" * 60)
    assert err.value.status == 400
    assert "vertex 3 is not finite" in str(err.value)
    assert "replace NaN/Inf values in vertex 3" in str(err.value)


def test_server_failure_is_not_called_a_refusal(server: str) -> None:
    with pytest.raises(client.ServiceError, match="The service failed on POST") as err:
        client.Client(server).build_bvh("0" * 32, "sah", 8)
    assert err.value.status == 500


def test_head_answers_known_and_unknown(server: str) -> None:
    c = client.Client(server)
    assert c.has_scene("known") and not c.has_scene("unknown")
    assert c.requests == ["HEAD /v1/scenes/known", "HEAD /v1/scenes/unknown"]


def test_slow_service_times_out_with_a_message(server: str) -> None:
    with pytest.raises(client.ServiceError, match="did not answer within 2 s"):
        client.Client(server).health()


def test_wrong_result_length_is_caught(server: str) -> None:
    with pytest.raises(client.ServiceError, match="sent 12 bytes for 2 pixels"):
        client.Client(server).job_result("0" * 16, 2, "depth")


def test_proxies_are_ignored(server: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A system proxy must not intercept local traffic: point one at a dead port."""
    monkeypatch.setenv("http_proxy", "http://127.0.0.1:9")
    monkeypatch.setenv("HTTP_PROXY", "http://127.0.0.1:9")
    assert client.Client(server).has_scene("known")


class _KeptAlive(BaseHTTPRequestHandler):
    """HTTP/1.1 that keeps connections open (as uvicorn does), counting them; with the
    server's `close_idle`, it closes each after one answer without saying so, as a
    server's idle timeout closes a kept connection between two calls."""

    protocol_version = "HTTP/1.1"

    def log_message(self, *args: object) -> None:
        pass

    def setup(self) -> None:
        super().setup()
        self.server.connections += 1  # type: ignore[attr-defined]

    def do_GET(self) -> None:  # noqa: N802
        body = b'{"status": "ok"}'
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)
        self.close_connection = self.server.close_idle  # type: ignore[attr-defined]


@pytest.mark.parametrize("close_idle", [False, True], ids=["kept", "closed-while-idle"])
def test_calls_share_a_connection_and_survive_its_closing(close_idle: bool) -> None:
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), _KeptAlive)
    httpd.connections, httpd.close_idle = 0, close_idle  # type: ignore[attr-defined]
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        c = client.Client(f"http://127.0.0.1:{httpd.server_address[1]}")
        assert [c.health() for _ in range(3)] == [{"status": "ok"}] * 3
        assert httpd.connections == (3 if close_idle else 1)  # type: ignore[attr-defined]
        c.close()
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_scene_id_rule() -> None:
    """sha256 of a header naming the counts, then the body: 32 hex characters."""
    import hashlib

    body = b"\1\2\3"
    expected = hashlib.sha256(b"scenesort-scene-v1 1 0\n" + body).hexdigest()[:32]
    assert client.scene_id(1, 0, body) == expected
    assert client.scene_id(0, 1, body) != expected  # same bytes, other split
