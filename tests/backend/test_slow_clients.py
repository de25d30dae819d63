"""Slow and greedy clients against a real `scenesort serve` on loopback: connections that
never finish their request head are dropped and do not take the places of requests, and
the token holder is served while strangers hold connections (api/server.py, the Guard's
counts in api/security.py). benchmarks/slow_clients.py measures the same for longer."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import httpx
import pytest
from dribble import Dribblers
from scenesort.backend.api.server import MAX_HEAD_BYTES
from service_client import Service

FLOOR_S = 1.0  # the slow-client floor: /v1/health answers the token holder within 1 s
WAIT_S = 30.0  # bound on every wait below


@pytest.fixture(scope="module")
def svc(start_service) -> Service:
    return start_service()  # the defaults: serve --head-timeout 5, --max-connections 64


@pytest.fixture(scope="module")
def quick(start_service) -> Service:
    return start_service("--head-timeout", "1")


def address(svc: Service) -> tuple[str, int]:
    host, port = svc.url.removeprefix("http://").rsplit(":", 1)
    return host, int(port)


def health(svc: Service, headers: dict[str, str]) -> httpx.Response:
    """GET /v1/health on a new connection, as the add-on sends it, answered within the
    floor (httpx's timeout bounds each phase; the floor is the whole request's)."""
    start = time.monotonic()
    answer = httpx.get(f"{svc.url}/v1/health", headers=headers, timeout=FLOOR_S)
    assert time.monotonic() - start < FLOOR_S
    return answer


def test_health_answers_the_token_holder_while_300_connections_dribble_their_heads(
    svc: Service,
) -> None:
    """Before, every connection still sending its head took one of uvicorn's places: with
    300 of them /v1/health answered 503."""
    with Dribblers(*address(svc), count=300) as slow:
        assert slow.wait_until(lambda d: d.sent >= 3 * d.count, WAIT_S)  # all are dribbling
        for _ in range(5):
            answer = health(svc, svc.auth)
            assert answer.status_code == 200 and answer.json()["device"] == "cpu", answer.text
            assert health(svc, {}).status_code == 200  # a stranger's probe too
        assert slow.open == 300


def test_a_connection_that_never_finishes_its_head_is_dropped(quick: Service) -> None:
    with Dribblers(*address(quick), count=20, reconnect=False) as slow:
        assert slow.wait_until(lambda d: d.dropped == d.count, WAIT_S), slow.dropped
    assert health(quick, quick.auth).status_code == 200


def test_a_connection_that_sends_nothing_is_dropped(quick: Service) -> None:
    with socket.create_connection(address(quick), timeout=WAIT_S) as sock:
        assert sock.recv(1) == b""  # closed by the service, not by the timeout here


def test_a_kept_alive_connection_gets_a_new_deadline_per_request(quick: Service) -> None:
    """The second request's head counts from its own first byte."""
    with httpx.Client(base_url=quick.url, headers=quick.auth, timeout=WAIT_S) as client:
        for _ in range(3):
            assert client.get("/v1/health").status_code == 200


def test_a_request_head_over_64_kib_is_431(svc: Service) -> None:
    """One byte over the bound, and no end of the head: the service has read every byte
    when it answers, so the answer cannot be lost to a reset."""
    start = f"GET /v1/health HTTP/1.1\r\nHost: 127.0.0.1:{address(svc)[1]}\r\nX-Big: ".encode()
    head = start + b"a" * (MAX_HEAD_BYTES + 1 - len(start))
    with socket.create_connection(address(svc), timeout=WAIT_S) as sock:
        sock.sendall(head)
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 431 "), answer[:200]
    assert health(svc, svc.auth).status_code == 200


@pytest.fixture
def idle_strangers(svc: Service) -> Iterator[list[socket.socket]]:
    """200 connections on which a stranger got its 401 and kept the connection open."""
    request = (f"GET /v1/scenes/{'0' * 32} HTTP/1.1\r\nHost: 127.0.0.1:{address(svc)[1]}"
               "\r\n\r\n").encode()
    held = []
    try:
        for _ in range(200):
            sock = socket.create_connection(address(svc), timeout=WAIT_S)
            held.append(sock)
            sock.sendall(request)
            assert sock.recv(65536).startswith(b"HTTP/1.1 401 ")
        yield held
    finally:
        for sock in held:
            sock.close()


def test_strangers_holding_connections_leave_the_token_holder_served(
    svc: Service, idle_strangers: list[socket.socket]
) -> None:
    """Before, 200 open connections were over uvicorn's cap (twice --max-connections): the
    token holder's requests got 503."""
    assert health(svc, svc.auth).status_code == 200
    missing = httpx.get(f"{svc.url}/v1/scenes/{'0' * 32}", headers=svc.auth, timeout=WAIT_S)
    assert missing.status_code == 404, missing.text
