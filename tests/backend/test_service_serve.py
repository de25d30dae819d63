"""`scenesort serve`: loopback by default, a token beyond it, clear refusals."""

from __future__ import annotations

import subprocess
import sys

import httpx

from backend.serve import is_loopback

REPO = __import__("pathlib").Path(__file__).resolve().parents[2]


def serve(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "backend.cli", "serve", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_refuses_a_public_host_without_a_token() -> None:
    result = serve("--host", "0.0.0.0", "--port", "0")
    assert result.returncode == 2
    assert "refusing to listen on 0.0.0.0" in result.stderr and "--token" in result.stderr


def test_refuses_an_unknown_device() -> None:
    result = serve("--device", "cuda:7", "--port", "0")
    assert result.returncode == 2 and "--device 'cuda:7' is not available" in result.stderr


def test_loopback_detection() -> None:
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.2")
    assert not is_loopback("myhost.example")


def test_token_is_required_when_given(start_service) -> None:
    guarded = start_service("--token", "s3cret")
    url = f"{guarded.url}/v1/scenes/{'0' * 32}"
    assert httpx.get(f"{guarded.url}/v1/health", timeout=10).status_code == 200  # open probe
    refused = httpx.get(url, timeout=10)
    assert refused.status_code == 401 and refused.json()["parameter"] == "Authorization"
    wrong = httpx.get(url, headers={"Authorization": "Bearer nope"}, timeout=10)
    assert wrong.status_code == 401
    right = httpx.get(url, headers={"Authorization": "Bearer s3cret"}, timeout=10)
    assert right.status_code == 404  # past the guard: the scene just is not there


def test_listening_socket_lets_asyncio_turn_nagle_off() -> None:
    """asyncio sets TCP_NODELAY only on IPPROTO_TCP sockets; without it each keep-alive
    answer waited ~40 ms for a delayed ACK (a regression seen with socket.create_server)."""
    import socket

    from backend.serve import _listen

    server = _listen(socket.AF_INET, "127.0.0.1", 0)
    with server, socket.create_connection(server.getsockname()) as client:
        accepted, _ = server.accept()
        with accepted:
            assert client.fileno() >= 0
            assert accepted.proto == socket.IPPROTO_TCP
